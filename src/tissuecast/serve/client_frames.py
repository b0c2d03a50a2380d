"""Coordinate frames of a serving session: tracker -> model for markers, model -> client for replies.

The model predicts in its mesh's frame, **LPS** mm (the scan's frame; see
:mod:`tissuecast.frames`). Around it:

- the **client frame** is where replies (``TissueSurface``, ``TissueField``) go and where
  markers arrive when no registration is set: ``LPS`` (the model/scan frame, default) or
  ``RAS`` (3D Slicer's world: OpenIGTLinkIF sends and receives RAS);
- a **registration** maps the tracker's frame (where PLUS or a tracking system reports
  marker positions) to the client frame. It comes from the config
  (``serve.tracker_to_client``, 16 numbers row by row) or at run time as an OpenIGTLink
  ``TRANSFORM`` named ``<From>To<Target>``, the SlicerIGT/PLUS way: ``TrackerToRas``,
  ``ReferenceToRas`` (target RAS: replies go back in RAS), ``TrackerToImage`` or
  ``TrackerToLps`` (target the scan/model frame, LPS). Once set, marker positions are read
  in the ``<From>`` frame, mapped to the model frame before prediction, and replies are
  sent in the target frame.

The state is shared by every connection of a server (one operating-room set-up): the
registration sent by Slicer on one connection applies to markers streamed by PLUS on another.
"""

from __future__ import annotations

import re

import numpy as np

from ..config import CLIENT_FRAMES, ServeConfig
from ..frames import LPS_TO_RAS, FrameError, apply_rotation, apply_transform, check_transform

__all__ = ["ClientFrames", "REGISTRATION_PATTERN", "CLIENT_FRAMES"]

#: device names of registration TRANSFORMs: <From>To<Target>, From not a marker name
REGISTRATION_PATTERN = re.compile(r"(?!Marker[0-9])([A-Za-z][A-Za-z0-9_]*?)To(Ras|RAS|Lps|LPS|Image)")
_TARGETS = {"Ras": "RAS", "RAS": "RAS", "Lps": "LPS", "LPS": "LPS", "Image": "LPS"}


class ClientFrames:
    """Where markers come from and where replies go (see the module docstring).

    Args:
        client_frame: ``"LPS"`` (the model's frame) or ``"RAS"`` (3D Slicer's world).
        tracker_to_client: (4, 4) or 16 numbers row by row, the registration from the
            tracker frame to the client frame; None = markers arrive in the client frame.

    Attributes:
        client_frame: the frame replies are sent in.
        tracker_to_model: (4, 4), maps incoming marker positions (mm) to the model frame.
        model_to_client: (4, 4), maps model-frame points to the client frame (identity for LPS).
        source: where the registration came from (``"config"``, a device name, or ``"none"``).
    """

    def __init__(self, client_frame: str = ServeConfig.client_frame, tracker_to_client=None):
        self.set(client_frame, tracker_to_client, "config" if tracker_to_client is not None else "none")

    def set(self, client_frame: str, tracker_to_client, source: str) -> None:
        """Replace the client frame and the registration (``tracker_to_client`` None = identity)."""
        if client_frame not in CLIENT_FRAMES:
            raise FrameError(f"client frame must be one of {CLIENT_FRAMES}, got {client_frame!r}")
        registration = np.eye(4) if tracker_to_client is None else check_transform(tracker_to_client, "tracker_to_client")
        self.client_frame = client_frame
        self.model_to_client = LPS_TO_RAS.copy() if client_frame == "RAS" else np.eye(4)
        self.tracker_to_model = np.linalg.inv(self.model_to_client) @ registration
        self.source = source
        self.identity_out = client_frame == "LPS"
        self.identity_in = bool(np.array_equal(self.tracker_to_model, np.eye(4)))

    def set_from_message(self, device_name: str, matrix: np.ndarray) -> bool:
        """Take a registration TRANSFORM; False if ``device_name`` is not one (see the pattern).

        Raises:
            FrameError: the matrix is singular or not affine.
        """
        match = REGISTRATION_PATTERN.fullmatch(device_name)
        if match is None:
            return False
        self.set(_TARGETS[match.group(2)], check_transform(matrix, f"TRANSFORM {device_name!r}"), device_name)
        return True

    def to_model(self, positions: np.ndarray) -> np.ndarray:
        """(n, 3) marker positions as received (mm) -> model frame (NaN rows stay NaN)."""
        return positions if self.identity_in else apply_transform(self.tracker_to_model, positions)

    def points_to_client(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) model-frame points (mm) -> client frame."""
        return points if self.identity_out else apply_transform(self.model_to_client, points)

    def vectors_to_client(self, vectors: np.ndarray) -> np.ndarray:
        """(n, 3) model-frame displacement vectors (mm) -> client frame."""
        return vectors if self.identity_out else apply_rotation(self.model_to_client, vectors)

    def describe(self) -> str:
        """One line for logs and the serve banner."""
        how = "markers in the client frame" if self.source == "none" else f"markers mapped by {self.source}"
        return f"replies in {self.client_frame}{' (model frame)' if self.identity_out else ''}; {how}"
