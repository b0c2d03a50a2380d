"""A sentinel marker: one planned marker that watches for tissue attached farther than simulated.

Where a scenario draws the attached region's extent (``[scenario.uncertain] attached_margin =
[lo, hi]``, mm along the surface), a region grown beyond ``hi`` holds vertices that no
simulation held. A marker on such a vertex moves in every simulated sample and stands still in
the operating room when the tissue is held there, which the alarm's stillness score reads
(:class:`tissuecast.surrogate.ood.MarkerStillness`). Markers planned for accuracy do not lie
there: those near the attached rim sit within the drawn range, where some draws hold them, and
the rest lie too far to be held by a region a few mm larger.

The sentinel is the surface vertex, at least ``min_distance`` from the other markers, between
``hi`` and ``hi + reach`` mm beyond the nominal region's edge
(``scenario/attached_distance``), whose least share of the markers' motion over the training
samples (its displacement over the markers' root-mean-square displacement, the sentinel
included, as the stillness score computes it) is largest: the one whose stillness is most
distinct from anything simulated, so tracking noise hides it least. It detects a region grown
by at least its own distance beyond the range (``reach`` or less). Ids 0-based; mm.
"""

from __future__ import annotations

import numpy as np

from ..surrogate.ood import fit_marker_stillness

__all__ = ["SENTINEL_REACH", "attached_range", "sentinel_marker"]

#: How far (mm, along the surface) beyond the drawn range's outer edge a sentinel may lie.
SENTINEL_REACH = 5.0


def attached_range(dataset) -> tuple[np.ndarray, float] | None:
    """``(signed surface distance (n,) mm from the nominal attached edge, largest drawn margin mm)``
    of a data set that draws the attached region's extent, else None (the store keeps the distance
    only where the margin is drawn: ``scenario/attached_distance``)."""
    distance = dataset.scenario_arrays.get("attached_distance")
    if distance is None:
        return None
    return np.asarray(distance, dtype=np.float64), float(dataset.config.scenario.uncertain.attached_margin[1])


def sentinel_marker(displacements, train_idx, markers, candidates, distance, margin_max: float, *, points=None,
                    min_distance: float = 0.0, reach: float = SENTINEL_REACH) -> tuple[int, float]:
    """The sentinel vertex for a set of planned markers (module docstring).

    Args:
        displacements: (N, n, 3) mm, every sample's field (only ``train_idx`` is read).
        train_idx: (N_t,) training samples.
        markers: (k,) 0-based ids of the other markers.
        candidates: (c,) 0-based ids a marker may use (surface, not fixed).
        distance: (n,) mm signed surface distance from the nominal attached edge (inf off the surface).
        margin_max: the largest margin drawn, mm.
        points: (n, 3) mm vertex positions (for ``min_distance``).
        min_distance: the sentinel lies at least this far (mm) from every other marker.
        reach: how far beyond the range's edge it may lie, mm.

    Returns:
        ``(vertex id, its least share)``, or ``(-1, 0.0)`` when no candidate qualifies.
    """
    cand = np.asarray(candidates, dtype=np.int64)
    d = np.asarray(distance, dtype=np.float64)[cand]
    band = cand[(d > margin_max) & (d <= margin_max + reach)]
    markers = np.asarray(markers, dtype=np.int64)
    if band.size and min_distance > 0 and markers.size:
        pts = np.asarray(points, dtype=np.float64)
        gap = np.linalg.norm(pts[band][:, None, :] - pts[markers][None, :, :], axis=2).min(axis=1)
        band = band[gap >= min_distance]
    if not band.size:
        return -1, 0.0
    train = np.asarray(train_idx, dtype=np.int64)
    fields = np.asarray(displacements[train], dtype=np.float64)
    others, own = fields[:, markers], fields[:, band]
    # each candidate's least share with the others, exactly as the stillness score fits it
    least = np.array([fit_marker_stillness(np.concatenate([others, own[:, [i]]], axis=1).reshape(len(train), -1)).least[-1]
                      for i in range(band.size)])
    best = int(np.argmax(least))
    return int(band[best]), float(least[best])
