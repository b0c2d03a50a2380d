"""Shared helpers of the benchmark tests (``tests/benchmarks``): loading a script of
``benchmarks/`` as a module, and the small spring-held scenario their stores use."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"

#: The embedded preset's supports on the small test box: no pins, the face whose outward
#: normals lie within 30 degrees of -z attached, springs on the rest, a gravity change.
SPRING_HELD = {"name": "embedded", "pins": False,
               "attached": {"rule": "normal", "direction": [0.0, 0.0, -1.0], "angle": 30.0},
               "springs": {"rule": "surface"}, "gravity": {"enabled": True}}


def load_benchmark(name: str):
    """``benchmarks/<name>.py`` as a module (its ``main`` not run). The folder is on
    ``sys.path`` while it loads, for scripts that import a neighbour."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec = importlib.util.spec_from_file_location(f"{name}_bench", BENCHMARKS / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    finally:
        sys.path.remove(str(BENCHMARKS))
