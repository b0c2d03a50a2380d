"""Each preset is stored once: the packaged ``tissuecast/configs/NAME.toml`` is the file, and
``configs/NAME.toml`` in the repository is a relative symlink to it. The other ``configs/*.toml``
are templates that need the user's mesh (``mesh.path`` set); every one of them loads."""

import os
import tomllib
from importlib import resources
from pathlib import Path

import pytest

from tissuecast.app.presets import preset_config, preset_names
from tissuecast.config import load_config
from tissuecast.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
REPO_CONFIGS = ROOT / "configs"
PACKAGE_CONFIGS = ROOT / "src" / "tissuecast" / "configs"


def test_the_presets_are_the_paper_quick_and_embedded_set_ups():
    assert {"paper", "quick", "embedded"} <= set(preset_names())
    assert preset_names() == sorted(p.stem for p in PACKAGE_CONFIGS.glob("*.toml"))


@pytest.mark.parametrize("name", preset_names())
def test_repository_config_is_a_relative_symlink_to_the_packaged_preset(name):
    link = REPO_CONFIGS / f"{name}.toml"
    assert link.is_symlink(), f"configs/{name}.toml must be a symlink to the packaged preset, not a copy"
    target = os.readlink(link)
    assert target == f"../src/tissuecast/configs/{name}.toml"  # relative: works in any checkout
    assert link.resolve() == (PACKAGE_CONFIGS / f"{name}.toml").resolve()
    packaged = (resources.files("tissuecast") / "configs" / f"{name}.toml").read_text(encoding="utf-8")
    assert link.read_text(encoding="utf-8") == packaged
    assert preset_config(name).name == name
    assert load_config(link) == preset_config(name)


def test_every_repository_config_loads_and_the_others_are_templates():
    presets = set(preset_names())
    templates = []
    for path in sorted(REPO_CONFIGS.glob("*.toml")):
        cfg = load_config(path)  # every file in configs/ is a valid config
        if path.stem in presets:
            assert path.is_symlink()
        else:
            templates.append(path.stem)
            # a template names the user's mesh; a config that runs as is belongs in the package
            assert not path.is_symlink() and cfg.mesh.path, f"configs/{path.name}: make it a packaged preset"
    assert "vessel" in templates


def test_the_wheel_carries_the_presets():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    assert "configs/*.toml" in pyproject["tool"]["setuptools"]["package-data"]["tissuecast"]


def test_an_unknown_preset_names_the_known_ones():
    with pytest.raises(ConfigError, match="no packaged preset 'nope'; use one of embedded, paper, quick"):
        preset_config("nope")
