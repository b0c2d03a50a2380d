"""Regions of the outer surface chosen by a rule (:class:`~tissuecast.config.RegionConfig`).

Rules: ``surface`` (every outer-surface vertex), ``ids`` (the surface vertices among given
0-based ids), ``tag`` (a named region of the mesh file, see :class:`~tissuecast.mesh.tags.MeshTags`),
``normal`` (surface vertices whose area-weighted outward normal lies within ``angle`` degrees of
``direction``: e.g. the posterior face) and ``distance`` (surface vertices within ``distance``
mm of ``point``). A region is a sorted array of surface vertex ids; one that comes out empty is
an error naming its config keys.
"""

from __future__ import annotations

import numpy as np

from ..config import RegionConfig
from ..errors import ConfigError, MeshError
from ..mesh.tags import MeshTags
from ..mesh.tetmesh import TetMesh
from ..mesh.surface import vertex_normals

__all__ = ["surface_region"]


def surface_region(mesh: TetMesh, rule: RegionConfig, key: str, tags: MeshTags | None = None,
                   normals: np.ndarray | None = None) -> np.ndarray:
    """The surface vertices a region rule selects.

    Args:
        mesh: the mesh (mm).
        rule: the region's settings.
        key: its config key, for messages (e.g. ``"scenario.attached"``).
        tags: the mesh file's named regions (rule ``tag``); None = none.
        normals: (n, 3) outward vertex normals if already computed (rule ``normal``).

    Returns:
        (k,) int64 sorted 0-based vertex ids on the outer surface; empty for rule ``none``.

    Raises:
        ConfigError: ids out of range, an unknown tag, or a rule that selects no surface vertex.
    """
    surface = mesh.surface_vertices
    if rule.rule == "none":
        return np.zeros(0, dtype=np.int64)
    if rule.rule == "surface":
        return np.asarray(surface, dtype=np.int64)
    if rule.rule == "ids":
        ids = np.asarray(rule.ids, dtype=np.int64)
        bad = ids[ids >= mesh.n_vertices]
        if bad.size:
            raise ConfigError(f"{key}.ids {bad.tolist()} are outside 0..{mesh.n_vertices - 1}; ids are 0-based "
                              "(subtract 1 from 1-based Abaqus/CalculiX ids)")
        chosen = np.intersect1d(ids, surface)
        what = f"ids {list(rule.ids)[:8]}{'...' if len(rule.ids) > 8 else ''} (none is on the outer surface)"
    elif rule.rule == "tag":
        try:
            chosen = np.intersect1d((tags or MeshTags()).vertices(rule.tag, rule.tag_value), surface)
        except MeshError as exc:
            raise ConfigError(f"{key}.tag: {exc}; set mesh.path to the file that holds it") from None
        value = "" if rule.tag_value == -1 else f" = {rule.tag_value}"
        what = f"tag {rule.tag!r}{value} (no vertex of it is on the outer surface)"
    elif rule.rule == "normal":
        n = vertex_normals(mesh) if normals is None else normals
        d = np.asarray(rule.direction, dtype=np.float64)
        cos = n[surface] @ (d / np.linalg.norm(d))
        chosen = surface[cos >= np.cos(np.radians(rule.angle)) - 1e-12]
        what = (f"outward normals within {rule.angle:g} degrees of {list(rule.direction)} (widen {key}.angle or "
                "change the direction)")
    elif rule.rule == "distance":
        dist = np.linalg.norm(mesh.points[surface] - np.asarray(rule.point, dtype=np.float64), axis=1)
        chosen = surface[dist <= rule.distance]
        what = (f"surface vertices within {rule.distance:g} mm of {list(rule.point)} (the nearest is "
                f"{dist.min():.3g} mm away)")
    else:  # pragma: no cover - the config refuses other rules
        raise ConfigError(f"{key}.rule = {rule.rule!r} is unknown")
    if chosen.size == 0:
        raise ConfigError(f"{key}: rule {rule.rule!r} selects no surface vertex: {what}")
    return np.asarray(chosen, dtype=np.int64)
