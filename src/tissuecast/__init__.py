"""tissuecast: real-time soft-tissue deformation from fiducial markers.

Pipeline (one sub-package per stage): ``mesh`` -> ``markers`` & ``forces`` -> ``fem`` ->
``dataset`` -> ``surrogate`` -> ``evaluate`` / ``serve``. Units: mm, N, MPa. Vertex ids are
0-based everywhere in the API.

Heavy modules (torch, zarr, pyvista...) are imported only when their names are first used.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

# public name -> module that defines it (imported lazily on first access)
_LAZY = {
    "TetMesh": "tissuecast.mesh",
    "read_mesh": "tissuecast.mesh",
    "write_mesh": "tissuecast.mesh",
    "phantom": "tissuecast.mesh",
    "select_markers": "tissuecast.markers",
    "select_fixed_vertices": "tissuecast.scenario.pins",
    "Config": "tissuecast.config",
    "load_config": "tissuecast.config",
    "NeoHookean": "tissuecast.fem",
    "Problem": "tissuecast.fem",
    "SolveResult": "tissuecast.fem",
    "solve": "tissuecast.fem",
    "lbo_basis": "tissuecast.forces",
    "simulate": "tissuecast.dataset",
    "open_dataset": "tissuecast.dataset",
    "DeformationModel": "tissuecast.surrogate",
    "plan_markers": "tissuecast.planning",
}

__all__ = sorted(_LAZY) + ["__version__", "errors"]


def __getattr__(name: str):
    if name == "errors":
        return importlib.import_module("tissuecast.errors")
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'tissuecast' has no attribute {name!r}")


def __dir__():
    return __all__
