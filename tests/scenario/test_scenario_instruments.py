"""Tracked instruments in the scenario and the data set: the pose rule (tissuecast.instruments),
the indentation probability's draw, the instrument section's checks, the poses a store records,
and a model trained and evaluated with them."""

from __future__ import annotations

import numpy as np
import pytest

from tissuecast.config import Config, with_overrides
from tissuecast.errors import ConfigError
from tissuecast.instruments import InstrumentPose, ReferenceSurface, features_from_arrays
from tissuecast.scenario import scenario_from_config, scenario_rng

from _surrogate_synthetic import box_mesh
from dataset_helpers import small_config

SCENARIO = {"name": "embedded", "pins": False,
            "attached": {"rule": "normal", "direction": [0.0, 0.0, -1.0], "angle": 30.0},
            "springs": {"rule": "surface"}, "gravity": {"enabled": True},
            "indentation": {"enabled": True, "radius": 11.0, "depth": [0.5, 1.5], "slide": [0.0, 0.5]}}
RETRACTOR = {"name": "retractor", "load": "indentation", "device": "RetractorToReference"}


def test_depth_and_contact_of_a_tool_tip_on_a_box():
    surface = ReferenceSurface.of(box_mesh())  # 20 x 25 x 40 mm, top face z = 40
    down = np.array([0.0, 0.0, -1.0])
    pose = surface.pose([10.0, 12.0, 37.5], down)
    assert pose.contact and pose.depth == pytest.approx(2.5, abs=1e-12)
    assert not surface.pose([10.0, 12.0, 41.0], down).contact and surface.pose([10.0, 12.0, 41.0], down).depth == 0.0
    up = surface.pose([10.0, 12.0, 37.5], [0.0, 0.0, 2.0])  # pushing up from below: 37.5 mm above the bottom face
    assert up.contact and up.depth == pytest.approx(37.5) and np.allclose(up.direction, [0, 0, 1])
    tilted = surface.pose([10.0, 12.0, 38.0], [0.6, 0.0, -0.8])  # back along the tool: 2 / 0.8 mm to the top face
    assert tilted.depth == pytest.approx(2.5, abs=1e-12)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # tool +z along -z
    flip[:3, 3] = [10.0, 12.0, 37.5]
    by_transform = surface.pose_from_transform(flip)
    assert by_transform.depth == pytest.approx(2.5) and np.allclose(by_transform.direction, down)
    np.testing.assert_array_equal(by_transform.features(), [10.0, 12.0, 37.5, 0.0, 0.0, -1.0, 2.5, 1.0])
    np.testing.assert_array_equal(InstrumentPose.away().features(), np.zeros(8))
    np.testing.assert_array_equal(features_from_arrays([[np.nan] * 3], [[np.nan] * 3], [0.0], [0]), np.zeros((1, 8)))
    with pytest.raises(ValueError, match="non-zero direction"):
        surface.pose([10.0, 12.0, 37.5], [0.0, 0.0, 0.0])


def _scenario(tmp_path, **indentation):
    cfg = small_config(tmp_path)
    sc = {**SCENARIO, "indentation": {**SCENARIO["indentation"], **indentation}, "instruments": [RETRACTOR]}
    return with_overrides(cfg, forces={"loading": "traction"}, scenario=sc)


def test_the_contact_draw_keeps_every_other_draw_and_poses_follow_the_indentation(tmp_path):
    _, _, _, always = scenario_from_config(_scenario(tmp_path))
    _, _, _, sometimes = scenario_from_config(_scenario(tmp_path, probability=0.6))
    seeds = np.random.default_rng(0).integers(0, 2**63, 400)
    touched = 0
    for s in seeds:
        base = always.draw(scenario_rng(s))
        a, b = always.draw_for(s), sometimes.draw_for(s)
        assert a.indentation.centre == base.indentation.centre  # probability 1: the draws as before
        np.testing.assert_array_equal(a.indentation.displacement, base.indentation.displacement)
        np.testing.assert_array_equal(b.gravity_direction, a.gravity_direction)
        (name, pose), = b.instruments
        assert name == "retractor" and pose.contact == (b.indentation is not None)
        if b.indentation is None:
            continue
        touched += 1
        ind = b.indentation
        np.testing.assert_array_equal(ind.displacement, a.indentation.displacement)
        np.testing.assert_array_equal(pose.tip, always.mesh.points[ind.centre] + ind.displacement)
        np.testing.assert_allclose(pose.direction, -ind.normal, atol=1e-15)
        # a convex body lies behind the tangent plane: the tip is at most the drawn depth deep
        assert 0.0 < pose.depth <= ind.depth + 1e-9
    assert abs(touched / len(seeds) - 0.6) < 4.5 * np.sqrt(0.6 * 0.4 / len(seeds))


def test_the_instrument_section_is_checked():
    base = {"indentation": {"enabled": True}}
    with pytest.raises(ConfigError, match="the scenario has no indentation"):
        with_overrides(Config(), scenario={"instruments": [RETRACTOR]})
    with pytest.raises(ConfigError, match="repeat a name"):
        with_overrides(Config(), scenario={**base, "instruments": [RETRACTOR, {**RETRACTOR, "device": "Other"}]})
    with pytest.raises(ConfigError, match="repeat a load"):
        with_overrides(Config(), scenario={**base, "instruments": [RETRACTOR, {"name": "b", "device": "Other"}]})
    with pytest.raises(ConfigError, match=r"device = 'Retractor To Reference' must be 1-20 ASCII"):
        with_overrides(Config(), scenario={**base, "instruments": [{**RETRACTOR, "device": "Retractor To Reference"}]})
    with pytest.raises(ConfigError, match="must start with a letter"):
        with_overrides(Config(), scenario={**base, "instruments": [{**RETRACTOR, "name": "2nd"}]})
    with pytest.raises(ConfigError, match=r"scenario.indentation.probability = 0.0 is out of range"):
        with_overrides(Config(), scenario={"indentation": {"probability": 0.0}})
    with pytest.raises(ConfigError, match=r"scenario.instruments\[0\].load = 'gravity' is not allowed"):
        with_overrides(Config(), scenario={**base, "instruments": [{**RETRACTOR, "load": "gravity"}]})


def test_a_store_records_the_poses_and_a_model_reads_them(tmp_path):
    from tissuecast.dataset import open_dataset, simulate
    from tissuecast.dataset.store import StoreWriter, data_config
    from tissuecast.errors import DatasetError
    from tissuecast.evaluate.evaluation import evaluate_model
    from tissuecast.surrogate import DeformationModel
    from tissuecast.surrogate.data import dataset_auxiliary

    cfg = with_overrides(_scenario(tmp_path, probability=0.6), forces={"target_max_displacement": 4.0},
                         dataset={"n_samples": 30, "n_test2": 0, "alpha": 0.0, "calibration_samples": 2,
                                  "predictor_samples": 6})
    path = tmp_path / "store.zarr"
    assert simulate(cfg, path, progress=False)["totals"]["failed"] == 0
    ds = open_dataset(path)
    poses = ds.instrument_poses["retractor"]
    centre, moved = ds.draws["indent_centre"], ds.draws["indent_displacement"]
    touching = centre >= 0
    np.testing.assert_array_equal(poses["contact"], touching.astype(np.int8))
    assert 0 < touching.sum() < len(touching)
    np.testing.assert_array_equal(poses["tip"][touching], ds.mesh.points[centre[touching]] + moved[touching])
    assert np.isnan(poses["tip"][~touching]).all() and (poses["depth"][~touching] == 0).all()
    features = dataset_auxiliary(ds, _inputs()).values
    assert (features[~touching] == 0).all() and (features[touching, 7] == 1).all()
    # the device name is for serving: another one continues the store, another probability does not
    assert "device" not in data_config(cfg)["scenario"]["instruments"][0]
    _, _, _, sc = scenario_from_config(cfg)
    renamed = with_overrides(cfg, scenario={"instruments": [{**RETRACTOR, "device": "SpatulaToTracker"}]})
    StoreWriter.resume(path, config=renamed, markers=ds.markers, scenario=sc)
    with pytest.raises(DatasetError, match="probability"):
        StoreWriter.resume(path, config=with_overrides(cfg, scenario={"indentation": {"probability": 0.5}}),
                           markers=ds.markers, scenario=sc)
    model = DeformationModel.from_dataset(ds, cfg, epochs=20, patience=0, calibration_share=0.0, n_components=4)
    assert model.auxiliary.names[0] == "retractor.tip_x" and model.fallback_ is not None
    result = evaluate_model(model, ds, splits=("test1",)).sets["test1"]
    assert np.isfinite(result.offsets["mlp"]).all()


def _inputs():
    from tissuecast.surrogate.auxiliary import AuxiliaryInputs, InstrumentInput

    return AuxiliaryInputs((InstrumentInput("retractor", "RetractorToReference"),))
