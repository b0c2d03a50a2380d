"""The edge where a :class:`~tissuecast.config.Config` meets the domain: the checks that need
to know what a file is.

:mod:`tissuecast.config` checks values on their own (types, ranges, keys that go together).
Whether a path names a label map, a closed surface or a volume mesh is known by the mesh
package, so those checks live beside the code that reads the files
(:func:`tissuecast.mesh.source.check_mesh_source`,
:func:`tissuecast.scenario.regions.check_region_source`,
:func:`tissuecast.evaluate.targets.check_target_source`), which also asks them when it uses the
section. :func:`check_config` asks them all at once, where the CLI and whole runs load a config,
so that a slip is one error naming its key before anything is computed.
"""

from __future__ import annotations

from pathlib import Path

from ..config import Config, load_config

__all__ = ["check_config", "load_run_config", "REGION_KEYS"]

#: The surface regions of ``[scenario]``: config key -> how to read it from a ScenarioConfig.
REGION_KEYS = {
    "scenario.attached": lambda sc: sc.attached,
    "scenario.springs": lambda sc: sc.springs,
    "scenario.indentation.access": lambda sc: sc.indentation.access,
}


def check_config(config: Config) -> Config:
    """Ask the domain's checks of a config's file paths (mesh source, region label maps, targets).

    Args:
        config: a config whose values :mod:`tissuecast.config` has checked.

    Returns:
        ``config`` itself.

    Raises:
        ConfigError: one line naming the key and the fix.
    """
    from ..evaluate.targets import check_target_source  # the domain, imported when asked
    from ..mesh.source import check_mesh_source
    from ..scenario.regions import check_region_source

    check_mesh_source(config.mesh, "mesh.")
    for key, region in REGION_KEYS.items():
        check_region_source(region(config.scenario), key)
    check_target_source(config.evaluate.targets, "evaluate.targets.")
    return config


def load_run_config(path: str | Path | None = None) -> Config:
    """:func:`~tissuecast.config.load_config` and :func:`check_config`: a config file (None = the
    defaults) as the CLI and whole runs take it."""
    return check_config(load_config(path))
