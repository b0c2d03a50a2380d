"""The packaged presets (``tissuecast/configs/*.toml``): every command that takes a config file
takes a preset's name instead (``tissuecast run embedded``, ``demo --preset NAME``)."""

from __future__ import annotations


def preset_names() -> list[str]:
    """Names of the packaged presets (``tissuecast/configs/*.toml``), sorted."""
    from importlib import resources

    folder = resources.files("tissuecast") / "configs"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def preset_config(name: str):
    """The packaged preset ``tissuecast/configs/NAME.toml`` as a Config (its values checked by
    :mod:`tissuecast.config`; :func:`.configuration.load_run_config` and whole runs check its
    paths)."""
    from importlib import resources

    from ..config import ConfigError, config_from_dict

    import tomllib

    res = resources.files("tissuecast") / "configs" / f"{name}.toml"
    if not res.is_file():
        raise ConfigError(f"no packaged preset {name!r}; use one of {', '.join(preset_names())}")
    return config_from_dict(tomllib.loads(res.read_text(encoding="utf-8")))
