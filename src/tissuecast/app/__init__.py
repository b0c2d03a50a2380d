"""Whole runs, at the edge beside the command line: simulate -> train -> evaluate -> report.

:mod:`.pipeline` strings the library's stages together as a config describes them (where a
run's files go, training from a store, the evaluation and its report, the whole run);
:mod:`.configuration` asks the domain's checks of a loaded config (what its paths name); the CLI
(:mod:`tissuecast.cli`) and scripts call it. Library packages never import it.
"""

from .configuration import check_config, load_run_config
from .pipeline import RunPaths, evaluate_and_report, resolve_source, run_paths, run_pipeline, train_from_store

__all__ = ["RunPaths", "run_paths", "train_from_store", "evaluate_and_report", "run_pipeline", "resolve_source", "check_config",
           "load_run_config"]
