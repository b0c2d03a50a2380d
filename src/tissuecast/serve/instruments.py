"""Tracked instruments on the wire: their TRANSFORMs in, their poses for the model, STATUS when lost.

A model trained with tracked instruments (``[[scenario.instruments]]``, :mod:`tissuecast.instruments`)
reads each instrument's pose. A tracker (PLUS, a navigation system) streams it as an OpenIGTLink
``TRANSFORM`` whose device name is the instrument's (``scenario.instruments[k].device``, e.g.
``RetractorTipToRef``): the tool's frame to the tracker's, its translation column the tool
tip (mm), its third column (the tool's local +z axis) the push direction. It is mapped into the
model frame as marker positions are (:class:`~tissuecast.serve.client_frames.ClientFrames`),
and the tip's depth below the reference surface and its contact follow from the model's mesh.

:class:`InstrumentTracking` (shared by every connection of a server, like the frames: PLUS may
stream the tool on one connection while Slicer sends markers on another) keeps each
instrument's latest pose and when it arrived (server clock). A prediction uses every pose
younger than ``serve.instrument_timeout`` seconds; an instrument whose TRANSFORMs have stopped
(or never came) is absent and the model predicts from the markers only (its fallback,
:mod:`tissuecast.surrogate.fallback`). Each connection is told when that changes: a STATUS
(device ``TissueStatus``) after the prediction's POLYDATA, code ``TIME_OUT`` and name
``InstrumentLost`` when an instrument is lost (or not tracked at the first prediction), code
``OK`` and name ``InstrumentTracked`` when it is back.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ..config import ServeConfig
from ..instruments import InstrumentPose, ReferenceSurface

__all__ = ["InstrumentTracking", "LOST_NAME", "TRACKED_NAME"]

LOST_NAME = "InstrumentLost"
TRACKED_NAME = "InstrumentTracked"


class InstrumentTracking:
    """The latest pose of each tracked instrument of a served model.

    Args:
        devices: ``{device name: instrument name}`` of the model's instruments.
        surface: the model mesh's :class:`~tissuecast.instruments.ReferenceSurface`.
        timeout: seconds after its last TRANSFORM an instrument counts as lost.
        clock: the time source (seconds; ``time.monotonic``, replaceable for tests).
    """

    def __init__(self, devices: dict[str, str], surface: ReferenceSurface | None,
                 timeout: float = ServeConfig.instrument_timeout, clock: Callable[[], float] = time.monotonic):
        self.devices = dict(devices)
        self.surface = surface
        self.timeout = float(timeout)
        self.clock = clock
        self._latest: dict[str, tuple[InstrumentPose, float]] = {}

    @property
    def names(self) -> list[str]:
        """The instruments' names, in the model's order."""
        return list(self.devices.values())

    def device_of(self, name: str) -> str:
        return next(d for d, n in self.devices.items() if n == name)

    def update(self, device: str, tool_to_model: np.ndarray) -> InstrumentPose:
        """Take a TRANSFORM of ``device`` already mapped into the model frame ((4, 4), mm)."""
        pose = self.surface.pose_from_transform(tool_to_model)
        self._latest[self.devices[device]] = (pose, self.clock())
        return pose

    def current(self) -> dict[str, InstrumentPose | None]:
        """``{instrument name: its pose, or None when lost}`` now."""
        now = self.clock()
        out = {}
        for name in self.names:
            latest = self._latest.get(name)
            out[name] = latest[0] if latest is not None and now - latest[1] <= self.timeout else None
        return out

    def lost_text(self, name: str) -> str:
        """The STATUS text of a lost instrument."""
        return (f"instrument {name!r} ({self.device_of(name)}): no TRANSFORM for {self.timeout:g} s; predicting "
                "from the markers only")

    def tracked_text(self, name: str) -> str:
        """The STATUS text of an instrument tracked again."""
        return f"instrument {name!r} ({self.device_of(name)}) tracked: predicting with its pose"
