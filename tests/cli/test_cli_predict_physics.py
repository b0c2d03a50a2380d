"""``tissuecast predict --physics``: the field of a tracked frame through the data set's simulator
(the physics inverse), its known loads from the tracked instrument's pose and the gravity
direction (``Scenario.frame_draw``), untracked markers, and the options' checks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tissuecast.cli.main import main
from tissuecast.errors import ConfigError, ModelError
from tissuecast.instruments import InstrumentPose
from tissuecast.scenario import scenario_from_config

from dataset_helpers import tracked_retractor_config as _config
from dataset_helpers import tracked_retractor_store


@pytest.mark.parametrize("tool", [{"tool": "flat"}, {"tool": "rounded", "tool_radius": 6.0}])
def test_a_tracked_pose_gives_back_the_drawn_indentation(tmp_path, tool):
    _, _, _, sc = scenario_from_config(_config(tmp_path, probability=1.0, **tool))
    for seed in range(40):
        draw = sc.draw_for(seed)
        (_, pose), = draw.instruments
        frame = sc.frame_draw({"retractor": pose}, draw.gravity_direction)
        a, b = draw.indentation, frame.indentation
        assert b.centre == a.centre
        np.testing.assert_array_equal(b.vertices, a.vertices)
        np.testing.assert_allclose(b.values, a.values, rtol=0, atol=1e-12)
        assert b.depth == pytest.approx(a.depth, abs=1e-12) and b.slide == pytest.approx(a.slide, abs=1e-12)
        np.testing.assert_allclose(frame.body_force, draw.body_force, rtol=1e-12, atol=0)
    away = sc.frame_draw({"retractor": InstrumentPose.away()})
    assert away.indentation is None  # the planned gravity direction: the cone's axis, so no change
    np.testing.assert_allclose(away.body_force, 0.0, atol=1e-15)
    with pytest.raises(ConfigError, match="pose of instrument 'retractor' is needed"):
        sc.frame_draw({})
    with pytest.raises(ConfigError, match=r"unknown instruments \['spatula'\]"):
        sc.frame_draw({"retractor": InstrumentPose.away(), "spatula": InstrumentPose.away()})
    # the retractor only where the surgery gives access (the middle of the top face): a push on a
    # side face, 18 mm along the surface from the access, is not a load this simulator draws
    access = {"rule": "distance", "point": [10.5, 16.0, 60.0], "distance": 6.0}
    _, _, _, top = scenario_from_config(_config(tmp_path, probability=1.0, access=access, **tool))
    side = top.reference_surface.pose([1.0, 1.0, 30.0], [1.0, 0.0, 0.0])
    assert side.contact
    with pytest.raises(ConfigError, match="cannot push the tissue there"):
        top.frame_draw({"retractor": side})
    # a tip reported in contact that lies outside the tissue (3 mm above the access) is refused
    assert top.frame_draw({"retractor": top.reference_surface.pose([10.5, 16.0, 59.0], [0.0, 0.0, -1.0])}).indentation
    above = InstrumentPose(np.array([10.5, 16.0, 63.0]), np.array([0.0, 0.0, -1.0]), 1.0, True)
    with pytest.raises(ConfigError, match=r"lies 3.00 mm outside the tissue at vertex \d+ yet is reported in contact"):
        top.frame_draw({"retractor": above})
    with pytest.raises(ConfigError, match="gravity direction must be a non-zero finite"):
        sc.frame_draw({"retractor": InstrumentPose.away()}, [0.0, 0.0, 0.0])


def test_predict_physics_recovers_a_test_sample_from_its_markers_and_instrument(tmp_path, capsys):
    from types import SimpleNamespace

    from tissuecast.cli.predict_physics import _dataset_for
    from tissuecast.dataset import open_dataset
    from tissuecast.inverse import MarkerInverse
    from tissuecast.surrogate import DeformationModel

    cfg, store, folder = tracked_retractor_store(tmp_path)
    ds, model = open_dataset(store), DeformationModel.load(folder)
    _, _, _, sc = scenario_from_config(cfg)
    idx = np.asarray(ds.select("test1", status="done"))
    i = int(next(j for j in idx if ds.draws["indent_centre"][j] >= 0))  # the retractor in contact
    truth = np.asarray(ds.displacements[i], dtype=np.float64)
    seed = int(ds.seed[i])
    draw = sc.draw_for(seed)
    (_, pose), = draw.instruments
    d = truth[model.markers]
    markers = tmp_path / "markers.json"
    markers.write_text(json.dumps({"displacements": d.tolist()}))
    inst = tmp_path / "retractor.json"
    inst.write_text(json.dumps({"retractor": {"tip": pose.tip.tolist(), "direction": pose.direction.tolist()}}))
    out = tmp_path / "u.json"
    base = ["predict", str(tmp_path / "model"), "--markers", str(markers), "--physics", str(store),
            "--instrument", str(inst), "--noise", "0.002"]
    assert main(base + ["--gravity", *map(str, draw.gravity_direction), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "solving through the physics" in text and "markers fitted to" in text and "1 sample(s)" in text
    assert "posterior spread median" in text
    written = json.loads(out.read_text())
    u, spread = np.array(written["displacement_mm"])[0], np.array(written["uncertainty_mm"])[0]
    assert spread.shape == (len(u),) and np.all(spread >= 0.0) and 0.0 < np.median(spread) < 0.01  # 0.002 mm noise
    (note,) = written["physics"]  # what the inverse estimated, one record a sample
    assert set(note["parameters"]) == set(MarkerInverse.from_dataset(ds, model.markers).estimated)
    assert note["marker_misfit_mm"] < 4 * 0.002 and not note["flagged"] and note["complete"]
    assert (note["held_sets"], note["estimate"], note["likeliest_weight"]) == (1, "mean", 1.0)
    assert note["solves"] > 0 and note["seconds"] > 0.0
    peak = np.linalg.norm(truth, axis=1).max()
    assert 0.5 < peak < 20.0
    assert np.linalg.norm(u - truth, axis=1).max() < 1e-3 * peak
    learned = model.predict(d, auxiliary={"retractor": pose})
    assert np.linalg.norm(learned - truth, axis=1).max() > 10 * np.linalg.norm(u - truth, axis=1).max()

    # a marker not tracked is left out of the fit; the answer stays close
    lost = d.copy()
    lost[1] = np.nan
    markers.write_text(json.dumps({"displacements": lost.tolist()}))
    assert main(base + ["--gravity", *map(str, draw.gravity_direction), "--out", str(out)]) == 0
    assert "missing markers [1]" in capsys.readouterr().out
    u = np.array(json.loads(out.read_text())["displacement_mm"])[0]
    assert np.linalg.norm(u - truth, axis=1).max() < 0.05 * peak

    for extra, why in ((["--uncertainty"], "--uncertainty belong to the learned model"),
                       (None, "give their poses with --instrument"),
                       (["--noise", "-1"], "--noise must be a positive number of mm"),
                       (["--time-limit", "-1"], "--time-limit must be a number of seconds >= 0"),
                       (["--attached-margin", "1.0"], "does not draw the attached region's margin")):
        argv = base + extra if extra is not None else base[:-4] + base[-2:]
        assert main(argv) == 2
        assert why in capsys.readouterr().err
    assert main(base[:4] + ["--physics", str(tmp_path / "nowhere.zarr"), "--instrument", str(inst)]) == 2
    assert "no data set there; give the store the model was trained on" in capsys.readouterr().err
    other = SimpleNamespace(mesh=SimpleNamespace(fingerprint=lambda: "another mesh"))
    with pytest.raises(ModelError, match="simulated on another mesh than the model's; give the store the model was"):
        _dataset_for(other, str(store))
    for extra in (["--noise", "0.1"], ["--physics-estimate", "mean"]):
        assert main(["predict", str(tmp_path / "model"), "--markers", str(markers), *extra]) == 2
        assert ("--gravity, --noise, --time-limit, --attached-margin(-sd) and --physics-estimate go with --physics"
                in capsys.readouterr().err)


def test_a_fit_that_misses_its_markers_is_flagged():
    from types import SimpleNamespace

    from tissuecast.cli.predict_physics import misfit_warning
    from tissuecast.inverse import MISFIT_NOISES, MarkerInverse

    inverse = SimpleNamespace(noise=0.05)  # MarkerInverse.flags on it: the study's physics rows count the same frames
    inverse.flags = lambda res: MarkerInverse.flags(inverse, res)
    assert misfit_warning(SimpleNamespace(marker_misfit=MISFIT_NOISES * 0.05 - 1e-9), inverse) is None
    assert MarkerInverse.flags(inverse, SimpleNamespace(marker_misfit=0.309))
    assert not MarkerInverse.flags(inverse, SimpleNamespace(marker_misfit=MISFIT_NOISES * 0.05 - 1e-9))
    text = misfit_warning(SimpleNamespace(marker_misfit=0.309), inverse)
    assert text.startswith("WARNING: a marker is 0.309 mm") and "6 x the tracking noise of 0.05 mm" in text


def test_an_inverse_with_more_unknowns_than_marker_coordinates_gets_a_note():
    from types import SimpleNamespace

    from tissuecast.cli.predict_physics import underdetermined_note

    assert underdetermined_note(SimpleNamespace(n_unknowns=22), 30) is None  # the embedded preset: 18 + 4, 10 markers
    text = underdetermined_note(SimpleNamespace(n_unknowns=60), 15)  # the paper preset: 20 LBO vectors, 5 markers
    assert text.startswith("note: the physics inverse estimates 60 unknowns from 15 marker coordinates")


def test_predict_physics_takes_a_measured_attached_margin(tmp_path, capsys, monkeypatch):
    """On a store that draws the attached margin, ``--attached-margin`` hands the measured one to
    the inverse: its held set alone is iterated (said so), the sample's field comes back, and a
    margin outside the simulated range is refused with the range. Searched, the inverse is asked
    for the posterior mean, or with ``--physics-estimate likeliest`` the likeliest held set's field."""
    from tissuecast.dataset import open_dataset
    from tissuecast.surrogate import DeformationModel

    cfg, store, folder = tracked_retractor_store(tmp_path, {"attached_margin": [-6.0, 6.0]})
    ds, model = open_dataset(store), DeformationModel.load(folder)
    _, _, _, sc = scenario_from_config(cfg)
    i = int(np.asarray(ds.select("test1", status="done"))[0])
    truth = np.asarray(ds.displacements[i], dtype=np.float64)
    margin = float(np.asarray(ds.parameters["attached_margin"])[i])
    draw = sc.draw_for(int(ds.seed[i]))
    (name, pose), = draw.instruments
    markers, inst, out = tmp_path / "markers.json", tmp_path / "retractor.json", tmp_path / "u.json"
    markers.write_text(json.dumps({"displacements": truth[model.markers].tolist()}))
    tool = {"contact": False} if not pose.contact else {"tip": pose.tip.tolist(), "direction": pose.direction.tolist()}
    inst.write_text(json.dumps({name: tool}))
    base = ["predict", str(folder), "--markers", str(markers), "--physics", str(store), "--instrument", str(inst),
            "--noise", "0.002", "--gravity", *map(str, draw.gravity_direction), "--out", str(out)]
    assert main(base + ["--attached-margin", f"{margin!r}"]) == 0
    assert f"iterated with the attached margin given ({margin:+.2f} mm)" in capsys.readouterr().out
    u = np.array(json.loads(out.read_text())["displacement_mm"])[0]
    assert np.linalg.norm(u - truth, axis=1).max() < 0.02 * np.linalg.norm(truth, axis=1).max()
    assert main(base + ["--attached-margin", "9.5"]) == 2
    assert "lies outside the range the simulations drew, [-6, 6] mm" in capsys.readouterr().err
    # searched: the posterior mean by default, the likeliest held set's field when asked
    from tissuecast.inverse import MarkerInverse

    asked, solve = [], MarkerInverse.solve

    def recording(self, *args, **kwargs):  # the estimate solved with, the margin and its sd handed over
        res = solve(self, *args, **kwargs)
        asked.append((res.estimate, kwargs["attached_margin"], kwargs["attached_margin_sd"]))
        return res

    monkeypatch.setattr(MarkerInverse, "solve", recording)
    assert main(base) == 0 and main(base + ["--physics-estimate", "likeliest"]) == 0
    # a measured margin with its uncertainty: searched with it as the prior (the estimate may be chosen)
    assert main(base + ["--attached-margin", "1.0", "--attached-margin-sd", "1.5", "--physics-estimate", "likeliest"]) == 0
    assert "attached margin measured +1.00 +- 1.5 mm" in capsys.readouterr().out
    assert asked == [("mean", None, None), ("likeliest", None, None), ("likeliest", 1.0, 1.5)]
    assert main(base + ["--attached-margin-sd", "1.5"]) == 2
    assert "--attached-margin-sd is the measured margin's uncertainty: give the margin" in capsys.readouterr().err
    assert json.loads(out.read_text())["physics"][0]["estimate"] == "likeliest"
    with pytest.raises(SystemExit):
        main(base + ["--physics-estimate", "median"])
    assert "invalid choice: 'median' (choose from 'mean', 'likeliest')" in capsys.readouterr().err
    assert main(base + ["--physics-estimate", "mean", "--attached-margin", f"{margin!r}"]) == 2
    assert "with --attached-margin alone one held set is solved: drop one of the two" in capsys.readouterr().err


def test_the_estimate_options_offer_the_inverses_estimates():
    """``predict --physics-estimate`` and ``study mismatch --physics-estimate`` offer
    :data:`~tissuecast.inverse.ESTIMATES` (the command line does not import the inverse to say so)."""
    import argparse

    from tissuecast.cli.predict_cmd import register as predict_parser
    from tissuecast.cli.study_cmd import register as study_parser
    from tissuecast.inverse import ESTIMATES

    for add in (predict_parser, study_parser):
        sub = argparse.ArgumentParser().add_subparsers()
        add(sub)
        (parser,) = sub.choices.values()
        (action,) = [a for a in parser._actions if a.dest == "physics_estimate"]
        assert tuple(action.choices) == ESTIMATES and action.default is None  # None: the inverse's default


def test_the_estimate_line_says_which_field_was_written():
    from types import SimpleNamespace

    from tissuecast.cli.predict_physics import describe

    p = SimpleNamespace(attached_margin=2.5, youngs_modulus=1.5)
    res = SimpleNamespace(parameters=p, marker_misfit=0.012, held_sets=4, estimate="likeliest", complete=True,
                          spread=np.array([0.0, 0.1, 0.3]), solves=40, seconds=12.0, likeliest_weight=0.614)
    text = describe(res, ("youngs_modulus",))
    assert text.startswith("markers fitted to 0.012 mm, youngs_modulus 1.5, attached margin +2.50 mm (the likeliest "
                           "of 4 held sets, 61 % of the posterior)") and "median 0.100 / max 0.300 mm; 40 solves, 12.0 s" in text
    assert "(4 held sets averaged, the likeliest 61 % of the posterior)" in describe(
        SimpleNamespace(**{**vars(res), "estimate": "mean"}))
    assert "held sets" not in describe(SimpleNamespace(**{**vars(res), "held_sets": 1}))
