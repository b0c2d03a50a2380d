"""Auxiliary model inputs: what a model reads besides the marker displacements.

Two kinds, one mechanism:

- the pose of each tracked **instrument** (``[[scenario.instruments]]``,
  :mod:`tissuecast.instruments`): 8 inputs ``<name>.tip_x, tip_y, tip_z`` (mm, model frame LPS),
  ``<name>.direction_x, _y, _z`` (unit push direction), ``<name>.depth`` (mm) and
  ``<name>.contact`` (1/0), all 0 when the instrument is away from the tissue;
- each uncertain parameter declared **measured** (``scenario.uncertain.measured``, e.g. E by
  elastography): one input ``<name>`` in the unit a data set records it in
  (``samples/param_<name>``: a factor on the nominal value, Poisson's ratio itself, the
  attached region's margin in mm).

An :class:`AuxiliaryInputs` names them (instruments first, in order, then the parameters), with
units, and turns what a caller gives into the (B, n_a) array the model reads
(:meth:`AuxiliaryInputs.batch`). The learned parts read ``x = [d, a]``: the marker
displacements d (3 n_d) then these n_a values, standardised inside the model with the training
set's statistics (:mod:`.mlp`, :mod:`.quadratic`), so no caller scales them.

An instrument can be **absent** (its tracking lost): all its inputs NaN. A model with
instrument inputs then predicts with its fallback, trained without them
(:mod:`.fallback`). A model without auxiliary inputs has an empty :class:`AuxiliaryInputs`
(width 0): everything it did before, bit for bit.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ..errors import ModelError
from ..instruments import POSE_FEATURES, POSE_UNITS, InstrumentPose, pose_features

__all__ = ["AuxiliaryInputs", "AuxiliaryValues", "InstrumentInput", "PARAMETER_UNITS", "MARKERS_ONLY"]

#: The unit of each per-sample parameter a data set records (``samples/param_<name>``).
PARAMETER_UNITS = {"youngs_modulus": "factor", "poisson_ratio": "1", "density": "factor", "spring_normal": "factor",
                   "spring_tangential": "factor", "attached_margin": "mm"}


@dataclass(frozen=True)
class InstrumentInput:
    """A tracked instrument the model reads: its name and the OpenIGTLink device of its TRANSFORM."""

    name: str
    device: str = ""


@dataclass(frozen=True)
class AuxiliaryInputs:
    """The auxiliary inputs of a model (module notes).

    Attributes:
        instruments: the tracked instruments, in input order.
        parameters: the measured parameters' names (keys of :data:`PARAMETER_UNITS`), in order.
    """

    instruments: tuple[InstrumentInput, ...] = ()
    parameters: tuple[str, ...] = ()

    def __post_init__(self):
        unknown = [p for p in self.parameters if p not in PARAMETER_UNITS]
        if unknown:
            raise ModelError(f"measured parameters {unknown} are not recorded per sample; a model can read "
                             f"{sorted(PARAMETER_UNITS)} (region_youngs_modulus: not yet)")

    @classmethod
    def from_config(cls, scenario) -> "AuxiliaryInputs":
        """The inputs a :class:`~tissuecast.config.ScenarioConfig` declares: its instruments and
        its ``uncertain.measured`` parameters."""
        return cls(tuple(InstrumentInput(i.name, i.device) for i in scenario.instruments),
                   tuple(scenario.uncertain.measured))

    # ------------------------------------------------------------------ layout
    @property
    def names(self) -> tuple[str, ...]:
        """(n_a,) input names: ``<instrument>.<feature>`` then the parameters."""
        return tuple(f"{i.name}.{f}" for i in self.instruments for f in POSE_FEATURES) + tuple(self.parameters)

    @property
    def units(self) -> tuple[str, ...]:
        """(n_a,) the inputs' units (mm, 1 = dimensionless, factor = on the nominal value)."""
        return POSE_UNITS * len(self.instruments) + tuple(PARAMETER_UNITS[p] for p in self.parameters)

    @property
    def width(self) -> int:
        """n_a, the number of auxiliary inputs."""
        return len(POSE_FEATURES) * len(self.instruments) + len(self.parameters)

    @property
    def instrument_columns(self) -> np.ndarray:
        """(8 k,) int column indices of the instruments' inputs."""
        return np.arange(len(POSE_FEATURES) * len(self.instruments))

    def without_instruments(self) -> "AuxiliaryInputs":
        """The inputs of this model's fallback: the parameters only."""
        return AuxiliaryInputs((), self.parameters)

    # ------------------------------------------------------------------ values
    def refuse_unread(self, given) -> None:
        """Refuse auxiliary inputs given to a model that reads none (``given`` None, an empty
        mapping or an empty array pass): a caller must not believe a pose or parameter is used.

        Raises:
            ModelError: naming the fix.
        """
        if self.width or given is None or (len(given) == 0 if isinstance(given, Mapping) else np.size(given) == 0):
            return
        raise ModelError("this model reads the markers only; auxiliary inputs (instrument poses, measured parameters) "
                         "need a model trained with [[scenario.instruments]] or scenario.uncertain.measured: drop "
                         "auxiliary=")

    def batch(self, given, batch: int) -> np.ndarray | None:
        """The (B, n_a) float64 inputs of ``batch`` samples from what a caller gives.

        Args:
            given: None (every instrument absent; a model with parameters refuses it), an array
                (n_a,) or (B, n_a) in :attr:`names` order and :attr:`units`, or a mapping
                ``{instrument name: InstrumentPose, or (B,) list of them, or None (absent);
                parameter name: value or (B,) values}``; an instrument left out is absent.
            batch: B.

        Returns:
            The inputs (absent instruments' columns NaN), or None for a model without
            auxiliary inputs (``given`` is then ignored: a composed model hands its inputs to
            parts that read none, e.g. the rigid baseline; :meth:`refuse_unread` is the
            public API's check).

        Raises:
            ModelError: wrong shape, unknown names, a missing parameter, NaN outside the
                instruments' columns, or a partly given instrument.
        """
        if not self.width:
            return None
        if given is None:
            given = {}
        if isinstance(given, Mapping):
            a = self._from_mapping(given, batch)
        else:
            a = self._from_array(given, batch)
        self._check(a)
        return a

    def _from_array(self, given, batch: int) -> np.ndarray:
        try:
            a = np.asarray(given, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ModelError(f"auxiliary inputs must be numbers, got {type(given).__name__}") from exc
        if a.shape == (self.width,):
            a = np.repeat(a[None], batch, axis=0)
        if a.shape != (batch, self.width):
            raise ModelError(f"auxiliary inputs must have shape ({self.width},) or ({batch}, {self.width}) for "
                             f"{list(self.names)}, got {a.shape}")
        return a.copy()

    def _from_mapping(self, given: Mapping, batch: int) -> np.ndarray:
        known = {i.name for i in self.instruments} | set(self.parameters)
        unknown = sorted(set(given) - known)
        if unknown:
            raise ModelError(f"unknown auxiliary inputs {unknown}; this model reads instruments "
                             f"{[i.name for i in self.instruments]} and parameters {list(self.parameters)}")
        missing = [p for p in self.parameters if given.get(p) is None]
        if missing:
            raise ModelError(f"this model needs the measured parameters {missing} "
                             f"({', '.join(PARAMETER_UNITS[p] for p in missing)}); give them, e.g. "
                             f"auxiliary={{{missing[0]!r}: 1.0}}")
        cols = []
        for inst in self.instruments:
            cols.append(_pose_columns(given.get(inst.name), batch, inst.name))
        for p in self.parameters:
            v = np.asarray(given[p], dtype=np.float64).reshape(-1)
            if v.size not in (1, batch):
                raise ModelError(f"parameter {p!r}: give one value or {batch}, got {v.size}")
            cols.append(np.broadcast_to(v, (batch,))[:, None])
        return np.hstack(cols)

    def _check(self, a: np.ndarray) -> None:
        k = len(self.instrument_columns)
        nan = np.isnan(a)
        if nan[:, k:].any() or np.isinf(a).any():
            raise ModelError(f"auxiliary inputs {list(self.names[k:])} must be finite (measured parameters)")
        n = len(POSE_FEATURES)
        for j, inst in enumerate(self.instruments):
            part = nan[:, j * n:(j + 1) * n]
            if (part.any(axis=1) & ~part.all(axis=1)).any():
                raise ModelError(f"instrument {inst.name!r}: give all {n} pose inputs or none (NaN = absent)")

    def absent(self, a: np.ndarray | None) -> np.ndarray:
        """(B,) bool: rows of inputs ``a`` (B, n_a) with an absent (NaN) instrument."""
        if a is None or not self.instruments:
            return np.zeros(0 if a is None else len(a), dtype=bool)
        return np.isnan(a[:, self.instrument_columns]).any(axis=1)

    # ------------------------------------------------------------------ record
    def as_dict(self) -> dict:
        """JSON-able record (``model.json``)."""
        return {"instruments": [{"name": i.name, "device": i.device} for i in self.instruments],
                "parameters": list(self.parameters), "names": list(self.names), "units": list(self.units)}

    @classmethod
    def from_dict(cls, d: dict | None) -> "AuxiliaryInputs":
        """From :meth:`as_dict` (None: a model without auxiliary inputs)."""
        if not d:
            return cls()
        return cls(tuple(InstrumentInput(i["name"], i.get("device", "")) for i in d.get("instruments", [])),
                   tuple(d.get("parameters", [])))


#: The inputs of a markers-only model: none besides the markers.
MARKERS_ONLY = AuxiliaryInputs()


def _pose_columns(value, batch: int, name: str) -> np.ndarray:
    """(B, 8) pose inputs of one instrument from a pose, a list of B poses, or None (absent: NaN)."""
    n = len(POSE_FEATURES)
    if value is None:
        return np.full((batch, n), np.nan)
    if isinstance(value, InstrumentPose):
        return np.repeat(value.features()[None], batch, axis=0)
    poses = list(value)
    if len(poses) != batch:
        raise ModelError(f"instrument {name!r}: give one pose or {batch}, got {len(poses)}")
    rows = [np.full(n, np.nan) if p is None else None for p in poses]
    given = [p for p in poses if p is not None]
    if given:
        if not all(isinstance(p, InstrumentPose) for p in given):
            raise ModelError(f"instrument {name!r}: poses must be tissuecast.instruments.InstrumentPose (or None)")
        feats = iter(pose_features(given))
        rows = [next(feats) if r is None else r for r in rows]
    return np.vstack(rows)


@dataclass(frozen=True, eq=False)
class AuxiliaryValues:
    """The auxiliary inputs of N samples (what a model is fitted on).

    Attributes:
        inputs: what they are (:class:`AuxiliaryInputs`).
        values: (N, n_a) float64 in ``inputs.names`` order and ``inputs.units``; an instrument
            away from the tissue has zeros (:mod:`tissuecast.instruments`).
    """

    inputs: AuxiliaryInputs
    values: np.ndarray

    def __post_init__(self):
        v = np.asarray(self.values, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != self.inputs.width:
            raise ModelError(f"auxiliary values must be (N, {self.inputs.width}) for {list(self.inputs.names)}, "
                             f"got {v.shape}")
        object.__setattr__(self, "values", v)
