"""The auxiliary inputs of ``tissuecast predict``: tracked instrument poses and measured parameters.

``--instrument FILE`` (JSON; points and directions in the model's frame, **LPS** mm, unless the
file says ``"frame": "RAS"``, 3D Slicer's world) gives each instrument's pose by name, for every
sample or as a list with one entry per sample::

    {"frame": "LPS",
     "retractor": {"tip": [x, y, z], "direction": [dx, dy, dz]}}        # depth and contact from the mesh
    {"retractor": {"transform": [[...], [...], [...], [0, 0, 0, 1]]}}  # tool -> model: tip = translation,
                                                                        # direction = the third column
    {"retractor": {"contact": false}}                                   # away from the tissue
    {"retractor": null}                                                 # not tracked: markers only
    [{"retractor": {...}}, {"retractor": {...}}]                        # one per sample

Depth and contact follow from the model's reference surface (:mod:`tissuecast.instruments`).
An instrument the file leaves out is not tracked: the model's fallback predicts from the markers.
``--parameter NAME=VALUE`` gives a measured parameter (``scenario.uncertain.measured``), in the
unit the model lists (a factor on the nominal value; Poisson's ratio; mm for the attached margin).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import ModelError
from ..frames import LPS_TO_RAS

__all__ = ["auxiliary_inputs", "read_instrument_file", "parse_parameters"]


def _pose(entry, surface, where: str):
    """One instrument's :class:`~tissuecast.instruments.InstrumentPose` (model frame), or None."""
    from ..instruments import InstrumentPose

    if entry is None:
        return None
    if not isinstance(entry, dict):
        raise ModelError(f"{where}: give {{'tip': [x, y, z], 'direction': [dx, dy, dz]}}, {{'transform': 4x4}}, "
                         f"{{'contact': false}} or null, got {entry!r}")
    try:
        if "transform" in entry:
            return surface.pose_from_transform(np.array(entry["transform"], dtype=np.float64))
        if "tip" in entry and "direction" in entry:
            return surface.pose(np.array(entry["tip"], dtype=np.float64), np.array(entry["direction"], dtype=np.float64))
    except ValueError as exc:
        raise ModelError(f"{where}: {exc}") from exc
    if entry.get("contact") is False and set(entry) == {"contact"}:
        return InstrumentPose.away()
    raise ModelError(f"{where}: give 'tip' and 'direction' (mm, unit vector), 'transform' (4x4) or 'contact': false; "
                     f"got keys {sorted(entry)}")


def _in_model_frame(entry, frame: str):
    """An entry's vectors mapped from ``frame`` (LPS or RAS) into the model frame (LPS)."""
    if frame == "LPS" or not isinstance(entry, dict):
        return entry
    flip = LPS_TO_RAS[:3, :3]  # its own inverse
    out = dict(entry)
    for key in ("tip", "direction"):
        if key in out:
            out[key] = (flip @ np.asarray(out[key], dtype=np.float64)).tolist()
    if "transform" in out:
        out["transform"] = (LPS_TO_RAS @ np.asarray(out["transform"], dtype=np.float64)).tolist()
    return out


def read_instrument_file(path: Path, names, surface, batch: int) -> dict:
    """``{instrument name: [B poses or None]}`` from an ``--instrument`` JSON file (module notes).

    Args:
        path: the file.
        names: the model's instrument names.
        surface: the model mesh's :class:`~tissuecast.instruments.ReferenceSurface`.
        batch: B, the number of samples predicted.

    Raises:
        ModelError: unreadable JSON, an unknown instrument or frame, a list of the wrong length.
    """
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise ModelError(f"cannot read the instrument file {str(path)!r}: {exc}") from exc
    samples = data if isinstance(data, list) else [data] * batch
    if len(samples) != batch or not all(isinstance(s, dict) for s in samples):
        raise ModelError(f"{str(path)!r}: give one object of instrument poses, or a list of {batch} (one per sample)")
    out = {name: [] for name in names}
    for b, sample in enumerate(samples):
        frame = sample.get("frame", "LPS")
        if frame not in ("LPS", "RAS"):
            raise ModelError(f"{str(path)!r}: frame {frame!r}; use 'LPS' (the model's) or 'RAS' (3D Slicer's)")
        unknown = sorted(set(sample) - set(names) - {"frame"})
        if unknown:
            raise ModelError(f"{str(path)!r}: unknown instruments {unknown}; this model reads {list(names)}")
        for name in names:
            out[name].append(_pose(_in_model_frame(sample.get(name), frame), surface, f"{path} sample {b} {name!r}"))
    return out


def parse_parameters(items) -> dict[str, float]:
    """``{name: value}`` from ``--parameter NAME=VALUE`` arguments."""
    out = {}
    for item in items or ():
        name, sep, value = item.partition("=")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            sep = ""
        if not sep or not name.strip():
            raise ModelError(f"--parameter {item!r}: write NAME=VALUE, e.g. youngs_modulus=1.3")
    return out


def auxiliary_inputs(model, instrument_file: str | None, parameters, batch: int) -> dict | None:
    """What ``model.predict(..., auxiliary=...)`` takes from the command line, or None for a
    markers-only model (which refuses the options)."""
    spec = model.auxiliary
    if not spec.width:
        if instrument_file or parameters:
            raise ModelError("this model reads the markers only; --instrument and --parameter need a model trained "
                             "with [[scenario.instruments]] or scenario.uncertain.measured")
        return None
    given = dict(parse_parameters(parameters))
    if instrument_file:
        from ..instruments import ReferenceSurface

        names = [i.name for i in spec.instruments]
        given.update(read_instrument_file(Path(instrument_file), names, ReferenceSurface.of(model.mesh), batch))
    return given
