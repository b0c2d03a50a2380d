"""JSON that every parser reads: the report's data files (``evaluation.json``, ``trust.json``,
``study_mismatch.json``) write a number that is not finite (NaN: not measured, e.g. a rank
correlation of too few samples; inf: an unbounded bound) as ``null``, not as the bare ``NaN`` /
``Infinity`` Python's ``json`` writes and JavaScript's ``JSON.parse`` refuses."""

from __future__ import annotations

import json
import math

import numpy as np

__all__ = ["dumps"]


def _finite(obj):
    """``obj`` with every non-finite float (Python or NumPy) replaced by None, NumPy scalars and
    arrays turned into Python numbers and lists."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def dumps(obj, **kwargs) -> str:
    """``json.dumps`` of ``obj`` with non-finite numbers as ``null`` (strict JSON: ``allow_nan``
    off, so anything left over raises instead of writing ``NaN``)."""
    return json.dumps(_finite(obj), allow_nan=False, **kwargs)
