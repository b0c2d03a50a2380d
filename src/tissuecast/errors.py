"""The exception hierarchy of tissuecast.

Every class subclasses :class:`TissuecastError` *and* the matching builtin, so callers can
catch either (``except ValueError`` keeps working). Messages say what was wrong, with the
offending value, and what to do about it.
"""

from __future__ import annotations

__all__ = [
    "TissuecastError",
    "MeshError",
    "MeshFormatError",
    "LabelMapError",
    "MarkerError",
    "MarkupsError",
    "FrameError",
    "ConfigError",
    "ConvergenceError",
    "SolveTimeout",
    "IterationLimit",
    "SolverSetupError",
    "DatasetError",
    "ModelError",
    "InputRejected",
    "RegistrationError",
    "DependencyError",
]


class TissuecastError(Exception):
    """Base class of every error raised on purpose by tissuecast."""


class MeshError(TissuecastError, ValueError):
    """A mesh is invalid (non-finite coordinates, bad indices, degenerate or inverted tets...)."""


class MeshFormatError(MeshError):
    """A mesh file is missing, of an unknown format, or holds no usable tetrahedra."""


class LabelMapError(MeshError):
    """A label map (segmented scan) cannot be meshed: unreadable, not 3-D, no spacing, an unknown
    or empty label or segment, or a label made of several pieces."""


class MarkerError(TissuecastError, ValueError):
    """Fiducial markers or fixed vertices cannot be chosen or are invalid."""


class MarkupsError(MarkerError):
    """A 3D Slicer markups file (.mrk.json, .fcsv) is unreadable or holds no usable point list."""


class FrameError(TissuecastError, ValueError):
    """A coordinate system or frame transform is unknown or unusable (not LPS/RAS, singular)."""


class ConfigError(TissuecastError, ValueError):
    """A configuration file or value is invalid (unknown key, wrong type, out of range)."""


class SolverSetupError(TissuecastError, ValueError):
    """A finite-element problem is ill-posed (rigid-body motion, forces on fixed vertices...)."""


class ConvergenceError(TissuecastError, RuntimeError):
    """The nonlinear solver stopped before reaching the full load.

    Attributes:
        load_fraction: fraction of the total load that was reached (0..1).
    """

    def __init__(self, message: str, load_fraction: float = 0.0, result=None):
        super().__init__(message)
        self.load_fraction = float(load_fraction)
        self.result = result


class SolveTimeout(ConvergenceError):
    """A solve was stopped because it ran past its time limit (``Solver.solve(time_limit=...)``).

    Attributes:
        seconds: how long it had run, s.  limit: the limit, s.
    """

    def __init__(self, message: str, seconds: float, limit: float):
        super().__init__(message)
        self.seconds = float(seconds)
        self.limit = float(limit)


class IterationLimit(ConvergenceError):
    """A solve was stopped because it needed more equilibrium iterations or numeric
    factorisations than it was allowed (``Solver.solve(iteration_limit=...,
    factorization_limit=...)``): a budget of work that, unlike a time limit, does not depend on
    the machine or its load.

    Attributes:
        iterations: the iterations it had used.  limit: the limit it ran into.
    """

    def __init__(self, message: str, iterations: int, limit: int):
        super().__init__(message)
        self.iterations = int(iterations)
        self.limit = int(limit)


class DatasetError(TissuecastError, ValueError):
    """A data-set store is unreadable, of another schema, or does not match the config."""


class ModelError(TissuecastError, ValueError):
    """A surrogate model is unfitted, incompatible, or given input of the wrong shape."""


class InputRejected(ModelError):
    """Marker input no simulation could have produced (non-finite, displaced far beyond every
    simulated sample, or markers at distances the body cannot take): refused by the input gate
    (:mod:`tissuecast.surrogate.gate`).

    Attributes:
        reason: ``"non-finite"``, ``"displacement"`` or ``"stretch"``.
        marker: index of the marker named (0-based, input order).  vertex: its vertex id (0-based).
        sample: index of the refused sample in the batch.
    """

    def __init__(self, message: str, *, reason: str = "", marker: int = -1, vertex: int = -1, sample: int = 0):
        super().__init__(message)
        self.reason, self.marker, self.vertex, self.sample = reason, int(marker), int(vertex), int(sample)


class RegistrationError(TissuecastError, ValueError):
    """A rigid registration is ill-posed (fewer than 3 points, collinear points, bad shapes)."""


class DependencyError(TissuecastError, ImportError):
    """An optional dependency (extra) is missing."""


def require(module: str, extra: str, purpose: str):
    """Import an optional dependency or raise :class:`DependencyError` naming the extra.

    Args:
        module: importable module name, e.g. ``"gmsh"``.
        extra: the pip extra that provides it, e.g. ``"mesh"``.
        purpose: what it is needed for, shown in the message.
    """
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DependencyError(
            f"{purpose} needs the Python package {module!r}, which is not installed "
            f"({exc}). Install it with: pip install 'tissuecast[{extra}]'"
        ) from exc
