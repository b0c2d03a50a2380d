"""The edge where a :class:`~tissuecast.config.Config` meets the domain: the checks that need
to know what a file is.

:mod:`tissuecast.config` checks values on their own (types, ranges, keys that go together).
Whether a path names a label map, a closed surface or a volume mesh is known by the mesh
package, so those checks live beside the code that reads the files
(:func:`tissuecast.mesh.source.check_mesh_source`,
:func:`tissuecast.scenario.regions.check_region_source`,
:func:`tissuecast.evaluate.targets.check_target_source`), which also asks them when it uses the
section. :func:`check_config` asks them all at once, where the CLI and whole runs load a config,
so that a slip is one error naming its key before anything is computed; with them, what a whole
run needs of sections that a model folder stores apart (:func:`check_nominal_expert`).
"""

from __future__ import annotations

from pathlib import Path

from ..config import UNCERTAIN_PARAMETERS, Config, load_config
from ..errors import ConfigError

__all__ = ["check_config", "check_nominal_expert", "check_run_sizes", "load_run_config", "REGION_KEYS"]

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
    check_nominal_expert(config)
    if config.surrogate.fallback_epochs and not config.scenario.instruments:
        raise ConfigError(f"surrogate.fallback_epochs = {config.surrogate.fallback_epochs} trains the markers-only "
                          "fallback of a model with tracked instruments, but scenario.instruments declares none; "
                          "remove fallback_epochs or declare the instrument ([[scenario.instruments]])")
    return config


def check_nominal_expert(cfg: Config) -> None:
    """A run with ``surrogate.nominal_expert`` needs parameters drawn (else the model is nominal
    already), none measured (the expert's store records no drawn value to read) and calibrated
    trust (the gate reads the alarms). A run-level check: a model folder's surrogate section is
    read without its scenario. ``surrogate.nominal_samples`` sizes that store: refused without it."""
    if not cfg.surrogate.nominal_expert:
        if cfg.surrogate.nominal_samples:
            raise ConfigError(f"surrogate.nominal_samples = {cfg.surrogate.nominal_samples} sizes the nominal expert's "
                              "store, but surrogate.nominal_expert is false; set nominal_expert = true or remove "
                              "nominal_samples")
        return
    u = cfg.scenario.uncertain
    if not any(getattr(u, name) for name in UNCERTAIN_PARAMETERS):
        raise ConfigError("surrogate.nominal_expert = true, but scenario.uncertain draws no parameter: the model is "
                          "nominal already; give a parameter a [min, max] range, or set nominal_expert = false")
    if u.measured:
        raise ConfigError(f"surrogate.nominal_expert = true with measured parameters {list(u.measured)}: the nominal "
                          "store draws none for the expert to read; remove one of the two")
    if cfg.surrogate.calibration == "none":
        raise ConfigError("surrogate.nominal_expert = true needs error bounds and alarms (the gate reads the alarms' "
                          "input distances); set surrogate.calibration = 'split' or 'cross-validation'")


#: Fewest samples of each split a whole run trains, validates and evaluates on.
RUN_MINIMUM = {"training": 2, "validation": 1, "test-1": 1}


def check_run_sizes(cfg: Config) -> None:
    """Refuse a data set (and the nominal expert's, if any) too small for a whole run: fewer
    training, validation or test-1 samples at ``dataset.split`` than :data:`RUN_MINIMUM`, found
    before anything is simulated.

    Raises:
        ConfigError: naming the counts and the smallest ``n_samples`` that gives enough.
    """
    from ..dataset.sample_plan import split_sizes

    stores = [("dataset.n_samples", cfg.dataset.n_samples)]
    if cfg.surrogate.nominal_expert:
        stores.append(("surrogate.nominal_samples", cfg.surrogate.nominal_samples or cfg.dataset.n_samples))
    need = tuple(RUN_MINIMUM.values())
    for key, n in stores:
        sizes = split_sizes(n, cfg.dataset.split)
        if all(have >= least for have, least in zip(sizes, need)):
            continue
        enough = next((m for m in range(n + 1, 100 * n + 100) if all(
            have >= least for have, least in zip(split_sizes(m, cfg.dataset.split), need))), None)
        ratio = ":".join(f"{r:g}" for r in cfg.dataset.split)
        got = ", ".join(f"{have} {name}" for have, name in zip(sizes, RUN_MINIMUM))
        fix = f"raise {key} to at least {enough} or change dataset.split" if enough else "change dataset.split"
        raise ConfigError(f"{key} = {n} at dataset.split {ratio} gives {got} samples; a run needs at least "
                          f"{', '.join(str(v) for v in need)}: {fix}")


def load_run_config(path: str | Path | None = None) -> Config:
    """:func:`~tissuecast.config.load_config` and :func:`check_config`: a config file (None = the
    defaults), or where no file of that name exists a packaged preset's name (``embedded``,
    :mod:`.presets`), as the CLI and whole runs take it.

    Raises:
        ConfigError: neither a file nor a preset (the message lists the presets), or the config
            is invalid.
    """
    from .presets import preset_config, preset_names

    if path is not None and not Path(path).is_file():
        if str(path) in preset_names():
            return check_config(preset_config(str(path)))
        if not Path(path).exists():
            raise ConfigError(f"config file {str(path)!r} does not exist and is no packaged preset; check the path, or "
                              f"name a preset: {', '.join(preset_names())} (`tissuecast config show NAME` prints one)")
    return check_config(load_config(path))
