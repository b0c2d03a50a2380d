"""Evaluation: accuracy metrics, parametric studies and the HTML report."""

from .metrics import PERCENTILES, SetSummary, offset_max, offset_mean, summarize, summarize_offsets, vertex_errors

__all__ = ["PERCENTILES", "SetSummary", "offset_max", "offset_mean", "summarize", "summarize_offsets", "vertex_errors"]
