"""The physics inverse: fields from the tracked markers by solving for the loads and the
unknown parameters with the data set's own simulator (:mod:`.solve`)."""

from .solve import ESTIMATES, MIN_TRACKED, MISFIT_NOISES, NOISE_MM, InverseResult, MarkerInverse, spread_band

__all__ = ["MarkerInverse", "InverseResult", "NOISE_MM", "MIN_TRACKED", "MISFIT_NOISES", "ESTIMATES", "spread_band"]
