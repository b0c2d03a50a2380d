"""Regions of the outer surface chosen by a rule (:class:`~tissuecast.config.RegionConfig`).

Rules: ``surface`` (every outer-surface vertex), ``ids`` (the surface vertices among given
0-based ids), ``tag`` (a named region of the mesh file, see :class:`~tissuecast.mesh.tags.MeshTags`),
``normal`` (surface vertices whose area-weighted outward normal lies within ``angle`` degrees of
``direction``: e.g. the posterior face) and ``distance`` (surface vertices within ``distance``
mm of ``point``). A region is a sorted array of surface vertex ids; one that comes out empty is
an error naming its config keys.

Three rules name a place in ways that carry over from one mesh to another (a preset written
on the phantom, used on a patient's mesh): ``markups`` (the points of a 3D Slicer markups
file, in the file's coordinate system converted to LPS, each moved to its nearest
outer-surface vertex, which must lie within ``snap`` mm; the region is the surface vertices
within ``distance`` mm of those vertices), ``extreme`` (the outer-surface vertex farthest
along ``direction``, or along the anatomical direction ``toward``, e.g. the most anterior
point; the region is the surface vertices within ``distance`` mm of it) and ``label`` (the
surface vertices in a voxel of a label map's label or in one of its 26 neighbours: e.g. the
bone a face rests on, segmented on the patient's scan). :func:`region_anchors` gives the
points a ``markups`` or ``extreme`` rule found, to show them.
"""

from __future__ import annotations

import numpy as np

from ..config import ANATOMICAL_DIRECTIONS, RegionConfig
from ..errors import ConfigError, MeshError
from ..mesh.labelmap import label_map_format
from ..mesh.tags import MeshTags
from ..mesh.tetmesh import TetMesh
from ..mesh.surface import vertex_normals

__all__ = ["surface_region", "region_anchors", "rule_direction", "check_region_source"]


def check_region_source(rule: RegionConfig, key: str) -> None:
    """Refuse a ``label`` rule whose ``label_map`` is not a label map file (by its name).

    Args:
        rule: the region's settings.
        key: its config key, for messages (e.g. ``"scenario.attached"``).

    Raises:
        ConfigError: naming ``{key}.label_map`` and the file kinds it reads.
    """
    if rule.rule == "label" and label_map_format(rule.label_map) is None:
        raise ConfigError(f"{key}.rule = 'label' needs {key}.label_map, a label map (.nii, .nii.gz, .nrrd, "
                          f".seg.nrrd), got {rule.label_map!r}")


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
        ConfigError: ids out of range, an unknown tag, a ``label`` rule without a label map
            (:func:`check_region_source`), or a rule that selects no surface vertex.
    """
    check_region_source(rule, key)
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
        d = rule_direction(rule)
        cos = n[surface] @ d
        chosen = surface[cos >= np.cos(np.radians(rule.angle)) - 1e-12]
        what = (f"outward normals within {rule.angle:g} degrees of {rule.toward or list(rule.direction)} (widen "
                f"{key}.angle or change the direction)")
    elif rule.rule in ("markups", "extreme", "label"):
        chosen, what = _place_region(mesh, rule, key)
    elif rule.rule == "distance":
        dist = np.linalg.norm(mesh.points[surface] - np.asarray(rule.point, dtype=np.float64), axis=1)
        chosen = surface[dist <= rule.distance]
        what = (f"surface vertices within {rule.distance:g} mm of {list(rule.point)} (the nearest is "
                f"{dist.min():.3g} mm away)")
    else:  # pragma: no cover - the config refuses other rules
        raise ConfigError(f"{key}.rule = {rule.rule!r} is unknown")
    if chosen.size == 0 and rule.rule == "distance":
        what += (f"; a point in the coordinates of another mesh does not carry over: give the place as a 3D Slicer "
                 f"point ({key}.rule = 'markups'), a direction ('extreme', e.g. {key}.toward = 'anterior') or a "
                 "label ('label')")
    if chosen.size == 0:
        raise ConfigError(f"{key}: rule {rule.rule!r} selects no surface vertex: {what}")
    return np.asarray(chosen, dtype=np.int64)


def rule_direction(rule: RegionConfig) -> np.ndarray:
    """(3,) unit vector of a rule's ``toward`` (LPS anatomical direction) or else its ``direction``."""
    d = np.asarray(ANATOMICAL_DIRECTIONS[rule.toward] if rule.toward else rule.direction, dtype=np.float64)
    return d / np.linalg.norm(d)


def region_anchors(mesh: TetMesh, rule: RegionConfig, key: str) -> np.ndarray:
    """(k,) int64 the surface vertices a ``markups`` rule's points snap to, or the ``extreme``
    rule's vertex; empty for the other rules (their region has no single place)."""
    if rule.rule == "markups":
        return _markup_vertices(mesh, rule, key)[0]
    if rule.rule == "extreme":
        surface = np.asarray(mesh.surface_vertices, dtype=np.int64)
        return surface[[int(np.argmax(mesh.points[surface] @ rule_direction(rule)))]]
    return np.zeros(0, dtype=np.int64)


def _near(mesh: TetMesh, anchors: np.ndarray, radius: float) -> np.ndarray:
    """Surface vertices within ``radius`` mm of any anchor vertex (the anchors included)."""
    surface = np.asarray(mesh.surface_vertices, dtype=np.int64)
    d = np.linalg.norm(mesh.points[surface][:, None, :] - mesh.points[anchors][None, :, :], axis=2).min(axis=1)
    return np.union1d(surface[d <= radius], anchors)


def _place_region(mesh: TetMesh, rule: RegionConfig, key: str) -> tuple[np.ndarray, str]:
    """(chosen surface vertices, what was asked) of the rules ``markups``, ``extreme`` and ``label``."""
    if rule.rule == "label":
        return _label_vertices(mesh, rule, key), (f"no outer-surface vertex lies in or next to the label of "
                                                   f"'{rule.label_map}' (is it in the mesh's frame?)")
    anchors = region_anchors(mesh, rule, key)
    return _near(mesh, anchors, rule.distance), f"within {rule.distance:g} mm of vertices {anchors.tolist()}"


def _markup_vertices(mesh: TetMesh, rule: RegionConfig, key: str) -> tuple[np.ndarray, np.ndarray]:
    """(the nearest surface vertex of each chosen markups point, the points (p, 3) LPS mm)."""
    from ..errors import MarkupsError
    from ..slicer.markups import read_markups

    try:
        lists = read_markups(rule.markups)
    except (MarkupsError, FileNotFoundError) as exc:
        raise ConfigError(f"{key}.markups: {exc}") from None
    points, labels = [], []
    for markup in lists:
        for xyz, label in zip(markup.positions, markup.labels):
            if rule.markup_label in ("", label, markup.name) and np.isfinite(xyz).all():
                points.append(xyz)
                labels.append(label)
    if not points:
        known = sorted({label for m in lists for label in m.labels} | {m.name for m in lists})
        which = f"with label {rule.markup_label!r} " if rule.markup_label else ""
        raise ConfigError(f"{key}: '{rule.markups}' holds no placed point {which}(labels and lists: "
                          f"{', '.join(known[:10]) or 'none'}); set {key}.markup_label")
    points = np.asarray(points, dtype=np.float64)
    surface = np.asarray(mesh.surface_vertices, dtype=np.int64)
    d = np.linalg.norm(mesh.points[surface][None, :, :] - points[:, None, :], axis=2)
    nearest = d.argmin(axis=1)
    far = d[np.arange(len(points)), nearest]
    if (far > rule.snap).any():
        k = int(np.argmax(far))
        raise ConfigError(f"{key}: point {labels[k]!r} of '{rule.markups}' lies {far[k]:.3g} mm from the outer surface, "
                          f"farther than {key}.snap = {rule.snap:g} mm; is the file in this mesh's frame (the scan the "
                          "mesh was made from)? Place the point on the surface, or raise the snap distance")
    return np.unique(surface[nearest]), points


def _label_vertices(mesh: TetMesh, rule: RegionConfig, key: str) -> np.ndarray:
    """Surface vertices in a voxel of the label, or in one of its 26 neighbours."""
    from scipy import ndimage

    from ..mesh.labelmap import read_label_map

    try:
        labelmap = read_label_map(rule.label_map, label=rule.label or None)
    except (MeshError, FileNotFoundError) as exc:
        raise ConfigError(f"{key}.label_map: {exc}") from None
    grown = ndimage.binary_dilation(labelmap.mask, structure=np.ones((3, 3, 3), dtype=bool))
    surface = np.asarray(mesh.surface_vertices, dtype=np.int64)
    ijk = np.rint(labelmap.to_ijk(mesh.points[surface])).astype(np.int64)
    inside = ((ijk >= 0) & (ijk < np.array(grown.shape))).all(axis=1)
    hit = np.zeros(len(surface), dtype=bool)
    hit[inside] = grown[tuple(ijk[inside].T)]
    return surface[hit]
