"""Intra-operative use: an OpenIGTLink server streaming predicted deformations.

Protocol summary (details in :mod:`tissuecast.serve.session` and
:mod:`tissuecast.serve.predictor`):

- in: ``POINT`` (n_d marker positions, mm, model marker order) or ``TRANSFORM``
  messages ``Marker0``..``Marker{n_d-1}`` (translation = marker position); a ``TRANSFORM``
  ``<From>To<Target>`` (``TrackerToRas``, ``ReferenceToRas``, ``TrackerToImage``) sets the
  registration: markers are then read in the tracker frame and replies go back in the
  target frame (:mod:`tissuecast.serve.client_frames`);
  ``GET_POLYDATA TissueField`` asks for the full field of the latest prediction.
- out: ``POLYDATA TissueSurface`` (deformed outer surface; ``uncertainty_mm`` point data
  for ensembles), ``POLYDATA TissueField`` (all vertices, ``displacement_mm`` vectors),
  ``STRING ERROR`` for rejected input. Reply timestamps copy the marker message's.
"""

from .client import IGTLClient, Reply
from .client_frames import ClientFrames
from .polydata import PolyData, PolyDataTemplate, decode_polydata
from .predictor import FIELD_DEVICE, SURFACE_DEVICE, Prediction, PredictionError, SurfacePredictor, served_predictor
from .protocol import ProtocolError
from .server import IGTLServer
from .session import ERROR_DEVICE, MARKER_PREFIX, ClientSession

__all__ = [
    "IGTLServer",
    "IGTLClient",
    "ClientFrames",
    "Reply",
    "ClientSession",
    "SurfacePredictor",
    "served_predictor",
    "Prediction",
    "PredictionError",
    "ProtocolError",
    "PolyData",
    "PolyDataTemplate",
    "decode_polydata",
    "SURFACE_DEVICE",
    "FIELD_DEVICE",
    "ERROR_DEVICE",
    "MARKER_PREFIX",
]
