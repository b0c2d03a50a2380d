"""Presurgical simulation data sets: plan, force calibration, parallel FEM solves, Zarr store.

``simulate(config)`` creates or continues a store (resumable, exact); ``open_dataset(path)``
reads one. The store layout is documented in :mod:`tissuecast.dataset.store` and
``docs/dataset-schema.md``.
"""

from .generate import data_config, recipe_from_store, setup_from_config, simulate
from .plan import SPLIT_CODES, SPLIT_NAMES, SamplePlan, make_plan, sample_seed
from .reader import Dataset, max_displacement_stats, open_dataset
from .codes import STATUS_NAMES, InitialGuess, SampleStatus
from .store import SCHEMA, SCHEMA_VERSION

__all__ = [
    "simulate",
    "recipe_from_store",
    "open_dataset",
    "Dataset",
    "make_plan",
    "SamplePlan",
    "sample_seed",
    "setup_from_config",
    "data_config",
    "max_displacement_stats",
    "SPLIT_NAMES",
    "SPLIT_CODES",
    "STATUS_NAMES",
    "SampleStatus",
    "InitialGuess",
    "SCHEMA",
    "SCHEMA_VERSION",
]
