"""Evaluation: accuracy metrics (Offset_max / Offset_mean, TRE at targets), parametric studies
and the HTML report."""

from .metrics import (PERCENTILES, SetSummary, TargetSummary, offset_max, offset_mean, share_corrected, summarize,
                      summarize_offsets, summarize_targets, target_errors, vertex_errors)
from .targets import Targets, interior_targets, label_targets, point_targets, targets_from_config, vertex_targets

__all__ = ["PERCENTILES", "SetSummary", "offset_max", "offset_mean", "summarize", "summarize_offsets", "vertex_errors",
           "TargetSummary", "target_errors", "share_corrected", "summarize_targets", "Targets", "interior_targets",
           "label_targets", "point_targets", "targets_from_config", "vertex_targets"]
