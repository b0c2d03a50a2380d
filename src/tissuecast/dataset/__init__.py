"""Presurgical simulation data sets: plan, force calibration, parallel FEM solves, Zarr store.

``simulate(config)`` creates or continues a store (resumable, exact); ``open_dataset(path)``
reads one. The store layout is documented in :mod:`tissuecast.dataset.schema` and
``docs/dataset-schema.md``.
"""

from .codes import STATUS_NAMES, InitialGuess, SampleStatus
from .generate import setup_from_config, simulate
from .reader import Dataset, max_displacement_stats, open_dataset, recipe_from_store
from .sample_plan import SPLIT_CODES, SPLIT_NAMES, SamplePlan, make_plan, sample_seed
from .schema import SCHEMA, SCHEMA_VERSION
from .store import data_config

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
