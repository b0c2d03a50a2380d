"""Data-driven fiducial-marker planning: choose marker vertices from simulated deformations.

``plan_markers(dataset, count=5)`` (or ``target_mm=1.0``) picks markers by QR-shortlisted
greedy forward selection on a quadratic proxy of the surrogate's validation error, refined
by exchanges; the planned ids train and evaluate like any user-given markers (``markers.ids``).
"""

from .candidates import REGIONS, candidate_vertices
from .plan import MarkerPlan, plan_markers, validation_error
from .proxy import QuadraticProxy
from .selection import exchange_markers, greedy_markers, qr_markers, qr_residuals

__all__ = ["plan_markers", "MarkerPlan", "validation_error", "candidate_vertices", "REGIONS", "QuadraticProxy",
           "greedy_markers", "exchange_markers", "qr_markers", "qr_residuals"]
