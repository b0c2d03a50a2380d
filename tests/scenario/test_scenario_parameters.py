"""Uncertain parameters drawn per sample: their distributions, the surface distance that sets
the attached extent, and what they do to the solve (E and the springs scaled together equal
the loads scaled down; the attached band held at zero; the density on the body loads)."""

from __future__ import annotations

import numpy as np
import pytest
from mesh_factories import box_grid
from scipy import stats

from tissuecast.config import Config, UncertainConfig, with_overrides
from tissuecast.errors import ConfigError
from tissuecast.fem import Solver
from tissuecast.scenario import build_scenario
from tissuecast.scenario.parameters import UncertainParameters, attached_distance, parameter_rng

BOX = box_grid(2, 2, 4, (5.0, 5.0, 5.0))  # 10 x 10 x 20 mm
BOTTOM = np.flatnonzero(np.isclose(BOX.points[:, 2], 0.0))


def _parameters(**ranges) -> UncertainParameters:
    m = 10
    return UncertainParameters(UncertainConfig(**ranges), np.full(m, 0.021), np.full(m, 0.45),
                               np.array([-1] * 5 + [0] * 5), 1)


def test_draws_are_reproducible_independent_of_the_other_ranges_and_follow_their_laws():
    full = _parameters(youngs_modulus=(0.5, 2.0), poisson_ratio=(0.40, 0.49), density=(0.9, 1.1),
                       spring_normal=(0.25, 4.0), attached_margin=(-5.0, 5.0), region_youngs_modulus=(1.0, 3.0))
    only_e = _parameters(youngs_modulus=(0.5, 2.0))
    draws = [full.draw(parameter_rng(s)) for s in range(3000)]
    again = [full.draw(parameter_rng(s)) for s in range(5)]
    assert draws[:5] == again
    assert [only_e.draw(parameter_rng(s)).youngs_modulus for s in range(50)] == [d.youngs_modulus for d in draws[:50]]
    e = np.array([d.youngs_modulus for d in draws])
    nu = np.array([d.poisson_ratio for d in draws])
    margin = np.array([d.attached_margin for d in draws])
    # log-uniform factors (as likely halved as doubled), uniform nu and margin: KS tests
    assert stats.kstest(np.log(e), stats.uniform(np.log(0.5), np.log(4.0)).cdf).pvalue > 0.01
    assert stats.kstest(nu, stats.uniform(0.40, 0.09).cdf).pvalue > 0.01
    assert stats.kstest(margin, stats.uniform(-5.0, 10.0).cdf).pvalue > 0.01
    kn = np.array([d.spring_normal for d in draws])
    rho = np.array([d.density for d in draws])
    region = np.array([d.region_youngs_modulus[0] for d in draws])
    assert stats.kstest(np.log(kn), stats.uniform(np.log(0.25), np.log(16.0)).cdf).pvalue > 0.01
    assert stats.kstest(np.log(region), stats.uniform(0.0, np.log(3.0)).cdf).pvalue > 0.01
    assert stats.kstest(rho, stats.uniform(0.9, 0.2).cdf).pvalue > 0.01  # density: a uniform factor
    assert stats.kstest(kn, stats.uniform(0.25, 3.75).cdf).pvalue < 1e-6  # not uniform in the factor itself
    # unset ranges keep the nominal values
    d = only_e.draw(parameter_rng(3))
    assert (np.isnan(d.poisson_ratio) and d.density == 1.0 and d.spring_normal == 1.0 and d.attached_margin == 0.0
            and d.region_youngs_modulus == (1.0,))
    # element constants: the global factor everywhere, the region's on its elements only
    e_el, nu_el = full.element_constants(draws[0])
    np.testing.assert_allclose(e_el[:5], 0.021 * draws[0].youngs_modulus)
    np.testing.assert_allclose(e_el[5:], 0.021 * draws[0].youngs_modulus * draws[0].region_youngs_modulus[0])
    np.testing.assert_allclose(nu_el, draws[0].poisson_ratio)


def test_a_nominal_share_keeps_that_share_of_samples_nominal_and_the_others_draws_unchanged():
    ranges = dict(youngs_modulus=(0.5, 2.0), poisson_ratio=(0.40, 0.49), attached_margin=(-5.0, 5.0),
                  region_youngs_modulus=(1.0, 3.0))
    plain, shared = _parameters(**ranges), _parameters(**ranges, nominal_share=0.3)
    n = 4000
    a = [plain.draw(parameter_rng(s)) for s in range(n)]
    b = [shared.draw(parameter_rng(s)) for s in range(n)]
    nominal = np.array([d.youngs_modulus == 1.0 and np.isnan(d.poisson_ratio) and d.attached_margin == 0.0
                        and d.region_youngs_modulus == (1.0,) for d in b])
    # the share is a binomial count: 0.3 within 4 standard deviations
    assert abs(nominal.mean() - 0.3) < 4.0 * np.sqrt(0.3 * 0.7 / n)
    # every other sample draws exactly what it draws without the share
    assert all(x == y for x, y, nom in zip(a, b, nominal) if not nom)
    np.testing.assert_equal([shared.draw(parameter_rng(s)).record() for s in range(20)], [d.record() for d in b[:20]])


def test_the_arcsine_law_makes_a_ranges_ends_likelier_and_leaves_the_other_draws_unchanged():
    """A parameter that ``arcsine`` names follows Beta(1/2, 1/2) over its range (on the log
    scale for factors; per region for the regions' E), its other draws and every other
    parameter's exactly as without it; the sensitivities' and the inverse's priors take the
    law's spread; names that are unknown or not drawn are refused with the fix."""
    from tissuecast.dataset.sensitivities import parameter_directions
    from tissuecast.scenario.parameters import law_cdf, law_quantile, law_sd

    ranges = dict(youngs_modulus=(0.5, 2.0), poisson_ratio=(0.40, 0.49), attached_margin=(-5.0, 5.0),
                  region_youngs_modulus=(1.0, 3.0))
    plain = _parameters(**ranges)
    ends = _parameters(**ranges, arcsine=("attached_margin", "youngs_modulus", "region_youngs_modulus"))
    n = 3000
    a = [plain.draw(parameter_rng(s)) for s in range(n)]
    b = [ends.draw(parameter_rng(s)) for s in range(n)]
    assert [d.poisson_ratio for d in a] == [d.poisson_ratio for d in b]  # not named: the same draws
    arcsine = stats.beta(0.5, 0.5)
    margin = np.array([d.attached_margin for d in b])
    t_e = np.log([d.youngs_modulus for d in b]) / np.log(4.0) + 0.5  # fraction of the log range
    t_region = np.log([d.region_youngs_modulus[0] for d in b]) / np.log(3.0)
    for t in ((margin + 5.0) / 10.0, t_e, t_region):
        assert stats.kstest(t, arcsine.cdf).pvalue > 0.01
        assert stats.kstest(t, stats.uniform(0.0, 1.0).cdf).pvalue < 1e-6
    # the same quantile mapped: a draw's uniform margin u gives sin(pi u / 2)^2 of the range
    u = (np.array([d.attached_margin for d in a]) + 5.0) / 10.0
    np.testing.assert_allclose(margin, -5.0 + 10.0 * law_quantile(u, True), atol=1e-12)
    # the ends three times likelier: within 5 % of the range's ends 14.4 % of the draws, not 5 %
    assert abs(np.mean(margin < -4.5) - law_cdf(0.05, True)) < 4.0 * np.sqrt(0.144 * 0.856 / n)
    assert law_cdf(0.05, True) == pytest.approx(2.0 / np.pi * np.arcsin(np.sqrt(0.05)))
    np.testing.assert_allclose(law_cdf(law_quantile(np.linspace(0, 1, 11), True), True), np.linspace(0, 1, 11),
                               atol=1e-12)
    assert law_sd(1.0, True) == pytest.approx(arcsine.std()) and law_sd(1.0, False) == pytest.approx(12 ** -0.5)

    class _Scenario:  # what parameter_directions reads
        def __init__(self, config):
            self.config, self.uncertain = config, object()

    for law in ((), ("youngs_modulus",)):
        (name, log, centre, sd), = parameter_directions(_Scenario(
            with_overrides(Config(), scenario={"uncertain": {"youngs_modulus": [0.5, 2.0], "arcsine": list(law)}}).scenario))
        assert (name, log, centre) == ("youngs_modulus", True, pytest.approx(0.0))
        assert sd == pytest.approx(np.log(4.0) / np.sqrt(8.0 if law else 12.0))
    for arcsine_names, message in ((["stiffness"], "arcsine names \\['stiffness'\\]; choose among"),
                                   (["density"], "arcsine names \\['density'\\], which scenario.uncertain does not draw")):
        with pytest.raises(ConfigError, match=message):
            with_overrides(Config(), scenario={"uncertain": {"attached_margin": [-5.0, 5.0], "arcsine": arcsine_names}})


def test_the_scenario_summary_names_each_uncertain_range_with_its_law():
    """`dataset info`, the evaluation table and the report list the drawn parameters, their
    ranges and laws (arcsine where named), the measured ones and the nominal share."""
    from tissuecast.scenario.describe import scenario_lines

    summary = {"name": "embedded", "uncertain": {"youngs_modulus": [0.5, 2.0], "density": [0.95, 1.05],
                                                 "attached_margin": [-5.0, 5.0], "measured": ["youngs_modulus"],
                                                 "nominal_share": 0.25, "arcsine": ["attached_margin"]}}
    rows = dict(scenario_lines(summary))
    assert rows["uncertain"] == ("drawn per sample: E x0.5-2 (log-uniform), density x0.95-1.05 (uniform), attached "
                                 "margin -5 to 5 mm (arcsine); measured (model inputs): youngs_modulus; 25 % of the "
                                 "samples nominal")
    summary["uncertain"]["arcsine"] = ["youngs_modulus"]
    assert dict(scenario_lines(summary))["uncertain"].startswith("drawn per sample: E x0.5-2 (arcsine in log),")
    assert "uncertain" not in dict(scenario_lines({"name": "embedded"}))


def test_the_signed_surface_distance_from_the_attached_rim():
    d = attached_distance(BOX, BOTTOM)
    side = np.flatnonzero(np.isclose(BOX.points[:, 0], 0.0) & (BOX.points[:, 2] > 0))
    np.testing.assert_allclose(d[side], BOX.points[side, 2])  # up the side along the vertical edges
    rim = BOTTOM[(BOX.points[BOTTOM, 0] % 10 == 0) | (BOX.points[BOTTOM, 1] % 10 == 0)]
    np.testing.assert_allclose(d[rim], -5.0)  # one edge below the first free vertex
    centre = BOTTOM[np.all(np.isclose(BOX.points[BOTTOM, :2], 5.0), axis=1)]
    np.testing.assert_allclose(d[centre], -10.0)
    assert np.isnan(d[np.setdiff1d(np.arange(BOX.n_vertices), BOX.surface_vertices)]).all()


def _box_config(tmp_path, gravity: bool = False, **uncertain) -> Config:
    from tissuecast.mesh import write_mesh

    path = tmp_path / "box.vtu"
    write_mesh(path, BOX)
    scenario = {"pins": False, "attached": {"rule": "normal", "direction": [0.0, 0.0, -1.0], "angle": 30.0},
                "springs": {"rule": "surface", "normal_stiffness": 0.002, "tangential_stiffness": 0.001},
                "gravity": {"enabled": gravity}, "uncertain": uncertain}
    return with_overrides(Config(), mesh={"path": str(path)}, solver={"order": 1},
                          forces={"loading": "traction", "n_basis": 6}, scenario=scenario)


def _scenario(cfg):
    from tissuecast.mesh import read_mesh

    return build_scenario(read_mesh(cfg.mesh.path), cfg, np.zeros(0, dtype=np.int64))


def test_E_and_springs_scaled_together_deform_like_the_loads_scaled_down(tmp_path):
    """Stresses scale with E and spring forces with k: the body of 2 E on 2 k springs under
    loads f moves as the nominal one under f / 2 (exactly, up to the solver's tolerance)."""
    nominal = _scenario(_box_config(tmp_path))
    cfg = _box_config(tmp_path, youngs_modulus=[2.0, 2.0], spring_normal=[2.0, 2.0], spring_tangential=[2.0, 2.0])
    stiff = _scenario(cfg)
    x = stiff.sample(5, alpha=1.5)
    assert x.parameters.youngs_modulus == 2.0 and x.materials is not None and x.springs is not None
    np.testing.assert_allclose(x.springs.stiffness, 2.0 * nominal.springs.stiffness, rtol=1e-12)
    tight = with_overrides(cfg, solver={"force_tolerance": 1e-8, "displacement_tolerance": 1e-8}).solver
    solver = Solver(nominal.problem(), tight)
    u_stiff = solver.with_parameters(*x.solver_parameters).solve(x.surface, **x.solve_keywords()).displacement
    u_half = solver.solve(x.surface / 2.0).displacement
    assert np.abs(u_half).max() > 0.5  # mm: large enough to be nonlinear
    np.testing.assert_allclose(u_stiff, u_half, atol=1e-6 * np.abs(u_half).max())
    # the view left the solver itself as it was
    np.testing.assert_allclose(solver.solve(x.surface / 2.0).displacement, u_half, rtol=0, atol=0)


def test_the_attached_extent_and_the_density_follow_the_draw(tmp_path):
    cfg = _box_config(tmp_path, attached_margin=[-5.0, 5.0])
    sc = _scenario(cfg)
    d = sc.uncertain.distance
    np.testing.assert_array_equal(sc.attached, np.flatnonzero(d <= -5.0))  # the smallest extent is static
    for seed in range(20):
        x = sc.sample(seed, alpha=0.05)
        m = x.parameters.attached_margin
        held = np.union1d(sc.attached, x.prescribed_ids)
        np.testing.assert_array_equal(held, np.flatnonzero(d <= m))
        assert not x.prescribed_values.any()
    grown = sc.sample(int(np.argmax([sc.sample(s, 0.05).parameters.attached_margin for s in range(20)])), alpha=0.05)
    u = Solver(sc.problem(), cfg.solver).solve(grown.surface, **grown.solve_keywords()).displacement
    assert not u[grown.prescribed_ids].any() and np.abs(u).max() > 0.1
    gravity = _box_config(tmp_path, gravity=True, density=[1.5, 1.5])
    plain = _box_config(tmp_path, gravity=True)
    a, b = _scenario(gravity).sample(3, 0.05), _scenario(plain).sample(3, 0.05)
    np.testing.assert_allclose(a.body, 1.5 * b.body, rtol=1e-15)


@pytest.mark.parametrize(
    "uncertain, scenario, text",
    [({"spring_normal": [0.5, 2.0]}, {}, "scenario.uncertain.spring_normal varies something this scenario lacks"),
     ({"density": [0.5, 2.0]}, {}, "set scenario.gravity.enabled"),
     ({"attached_margin": [-5.0, 5.0]}, {}, "set scenario.attached.rule"),
     ({"youngs_modulus": [2.0, 0.5]}, {}, "scenario.uncertain.youngs_modulus must be [min, max]"),
     ({"youngs_modulus": [0.5, 100.0]}, {}, "are factors on material.youngs_modulus"),
     ({"measured": ["E"]}, {}, "scenario.uncertain.measured names ['E']"),
     ({"measured": ["poisson_ratio"]}, {}, "which scenario.uncertain does not draw"),
     ({"nominal_share": 0.3}, {}, "nominal_share = 0.3 with no parameter drawn"),
     ({"youngs_modulus": [0.5, 2.0], "nominal_share": 1.0}, {}, "scenario.uncertain.nominal_share"),
     ({"youngs_modulus": [1.2, 2.0], "nominal_share": 0.3}, {},
      "draws samples at the nominal youngs_modulus"),
     ({"poisson_ratio": [0.40, 0.44], "nominal_share": 0.3}, {}, "outside scenario.uncertain.poisson_ratio"),
     ({"poisson_ratio": [0.40, 0.49], "measured": ["poisson_ratio"], "nominal_share": 0.3}, {},
      "cannot go with a measured poisson_ratio")],
)
def test_bad_uncertain_ranges_are_refused_naming_the_key(uncertain, scenario, text):
    with pytest.raises(ConfigError, match=text.replace("[", r"\[").replace("]", r"\]")):
        with_overrides(Config(), scenario={"uncertain": uncertain, **scenario})


def test_springs_scaled_alike_on_tilted_faces_stay_symmetric(tmp_path):
    """Normal and tangential parts scaled by (nearly) the same factor cancel off the diagonal;
    the sample's springs must still be exactly symmetric (a data set stopped on such a draw)."""
    import dataclasses

    from scipy.spatial.transform import Rotation

    from tissuecast.mesh import write_mesh
    from tissuecast.scenario.parameters import ParameterDraw

    tilted = dataclasses.replace(BOX, points=BOX.points @ Rotation.from_euler("xyz", [0.3, 0.5, 0.7]).as_matrix().T)
    path = tmp_path / "tilted.vtu"
    write_mesh(path, tilted)
    down = Rotation.from_euler("xyz", [0.3, 0.5, 0.7]).apply([0.0, 0.0, -1.0])
    scenario = {"pins": False, "attached": {"rule": "normal", "direction": list(down), "angle": 30.0},
                "springs": {"rule": "surface", "normal_stiffness": 0.002, "tangential_stiffness": 0.002},
                "uncertain": {"spring_normal": [0.25, 4.0], "spring_tangential": [0.25, 4.0]}}
    cfg = with_overrides(Config(), mesh={"path": str(path)}, solver={"order": 1},
                         forces={"loading": "traction", "n_basis": 6}, scenario=scenario)
    s = _scenario(cfg)
    for a, b in ((1.7, 1.7), (1.7, 1.7 * (1 + 1e-12)), (0.3, 2.9)):
        k = s.uncertain.springs(s.springs, ParameterDraw(spring_normal=a, spring_tangential=b)).stiffness
        np.testing.assert_array_equal(k, np.swapaxes(k, 1, 2))
        normal, tangential = s.uncertain.spring_parts
        np.testing.assert_allclose(k, a * normal + b * tangential, rtol=0, atol=1e-15 * np.abs(k).max())
